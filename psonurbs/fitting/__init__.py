"""The method: organise a cloud, parametrise it, swarm over knots and weights with control
points by least squares, polish and refine; the pipeline of one fit.

May import :mod:`psonurbs.geometry`, :mod:`psonurbs.config` and :mod:`psonurbs.errors`;
knows no files and no command line.
"""

"""Pure math: B-spline bases and knot vectors, the NURBS surface, control-net layouts.

May import only numpy and scipy (and :mod:`psonurbs.errors`): nothing of fitting, files,
runs or the command line.
"""

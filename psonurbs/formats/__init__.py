"""At the edge: reading point clouds, writing a fit's outputs, CAD exports.

May import :mod:`psonurbs.geometry` and :mod:`psonurbs.errors`; knows nothing of fitting.
"""

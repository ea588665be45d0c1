"""The method, in the order a fit runs it:

    prepare/     organise the cloud, the local outlier test, robust weights, big clouds
    parameters/  first (u, v) of every point: plane, intrinsic, closed, coarse to fine, topology
    leastsq/     control points by regularised least squares and its leave-one-out error
    search/      the swarm over knots, weights and smoothing; the held-out validation
    finish/      polish -> smoothing -> polish, the joint refinement, trims, self-checks
    pipeline.py  one fit, stage after stage; budget.py  what a cloud may cost

May import :mod:`psonurbs.geometry`, :mod:`psonurbs.config` and :mod:`psonurbs.errors`;
knows no files and no command line.
"""

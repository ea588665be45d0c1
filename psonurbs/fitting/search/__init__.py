"""The search: particle swarm optimisation (``swarm``) over a space of knots, weights and
the smoothing, the control points solved by least squares and each particle judged by
its leave-one-out RMSE (``knot_weight_space``; the paper's space of everything,
``paper_space``); the best kept only if it beats the classical fit on held-out points
by paired z-tests (``validation``).
"""

"""Control points by regularised least squares and the exact leave-one-out error.

    M P = R^T W X,   M = R^T W R + lam t / tr(L^T L) L^T L + kappa t / tr(C^T C) C^T C + ridge,
    e_i^loo = e_i / (1 - w_i r_i^T M^-1 r_i)

``regularised`` is the computation for one net; ``stacked`` the same for P particles
at once in numpy and ``stacked_compiled`` its numba twin; ``banded`` the banded
Cholesky and selected inverse they factor M with.
"""

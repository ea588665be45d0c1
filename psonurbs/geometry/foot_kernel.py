"""The compiled twin of the foot-point search (:mod:`psonurbs.geometry.projection`).

The same bounded Newton iteration, point by point instead of array by array: for each
point, the knot spans of (u, v), the basis values and derivatives on them, the rational
S, S_u, S_v, S_uu, S_uv, S_vv, the step H d = -g with the same convexity test, the
same active set on open edges and the same halving line search; closed directions wrap.
No array of the points' derivatives is ever formed, so a round costs a few microseconds
per point.

Every number is computed in the numpy reference's order of operations (the basis by
de Boor's recurrence as :func:`scipy.interpolate.BSpline.design_matrix` runs it, the
derivatives by the recurrence of :func:`psonurbs.geometry.basis.design_matrix`, the
tensor sums in the sparse matrix's column order), so the two paths agree to rounding.
Used by :func:`psonurbs.geometry.projection.closest_parameters` where
:data:`psonurbs.geometry.compiled.ENABLED`.
"""
from __future__ import annotations

import numpy as np

from .compiled import kernel


@kernel(inline=True)
def knot_span(t, degree, x):
    """The span l with t[l] <= x < t[l + 1] (the last non-empty one for x = t[n]),
    x already in [t[degree], t[n]]: scipy's ``find_interval``."""
    n = t.shape[0] - degree - 1
    span = degree + 1
    while span != n and x >= t[span]:
        span += 1
    return span - 1


@kernel(inline=True)
def deboor_values(t, degree, span, x, out, scratch):
    """out[0..degree] = N_{span-degree..span, degree}(x) (de Boor's recurrence, as scipy's
    ``_deBoor_D``). Knot indices are those of the full vector: the vector t[d:-d] of a
    lower degree p - d with its span l - d reads the same knots t[l + n], t[l + n - j]."""
    out[0] = 1.0
    for j in range(1, degree + 1):
        for n in range(j):
            scratch[n] = out[n]
        out[0] = 0.0
        for n in range(1, j + 1):
            xb, xa = t[span + n], t[span + n - j]
            if xb == xa:
                out[n] = 0.0
                continue
            w = scratch[n - 1] / (xb - xa)
            out[n - 1] += w * (xb - x)
            out[n] = w * (x - xa)


@kernel(inline=True)
def differentiate(t, degree, span, lower, out):
    """out[0..degree] = the derivative of the degree-``degree`` basis on its span from
    ``lower`` (the degree - 1 values, one order of derivative less):
    N'_{i,p} = p/(t_{i+p} - t_i) N_{i,p-1} - p/(t_{i+p+1} - t_{i+1}) N_{i+1,p-1}."""
    for c in range(degree + 1):
        left = t[span + c] - t[span - degree + c]
        right = t[span + c + 1] - t[span - degree + c + 1]
        a = degree / left if left > 0 else 0.0
        b = degree / right if right > 0 else 0.0
        below = lower[c - 1] if c >= 1 else 0.0
        above = lower[c] if c < degree else 0.0
        out[c] = a * below - b * above


@kernel(inline=True)
def basis_derivatives(t, degree, span, x, orders, out, work, scratch):
    """out[d, 0..degree] = d-th derivative of the basis on the span, d < ``orders`` (<= 3).

    Order d comes from the degree p - d values differentiated d times (degrees p-d+1 .. p
    in turn), as :func:`psonurbs.geometry.basis.design_matrix` does; a derivative of
    higher order than the degree is zero."""
    for d in range(orders):
        for c in range(degree + 1):
            out[d, c] = 0.0
        if d > degree:
            continue
        deboor_values(t, degree - d, span, x, work[0], scratch)
        for step in range(d):
            q = degree - d + step + 1
            differentiate(t, q, span, work[step], work[step + 1])
        for c in range(degree + 1):
            out[d, c] = work[d, c]


@kernel(inline=True)
def spline(bu, bv, du, dv, su, sv, degree_u, degree_v, nv, aw, w, out):
    """out[0:3] = sum_ab Bu[du, a] Bv[dv, b] (wP)_ab, out[3] = the same sum of the weights:
    the tensor basis row times the homogeneous net, in its sparse column order."""
    x, y, z, h = 0.0, 0.0, 0.0, 0.0  # sums in registers (out may alias the net for the compiler)
    for a in range(degree_u + 1):
        row = (su - degree_u + a) * nv + (sv - degree_v)
        for b in range(degree_v + 1):
            coefficient = bu[du, a] * bv[dv, b]
            x += coefficient * aw[row + b, 0]
            y += coefficient * aw[row + b, 1]
            z += coefficient * aw[row + b, 2]
            h += coefficient * w[row + b]
    out[0], out[1], out[2], out[3] = x, y, z, h


@kernel
def surface_jet(tu, tv, degree_u, degree_v, nv, aw, w, u, v, orders, bu, bv, work, scratch, homogeneous, jet):
    """jet[0] = S(u, v); with orders >= 2 also jet[1] = S_u, jet[2] = S_v; with orders = 3
    jet[3..5] = S_uu, S_uv, S_vv (the quotient rule of :meth:`NurbsSurface.derivatives`)."""
    u = min(max(u, tu[degree_u]), tu[tu.shape[0] - degree_u - 1])
    v = min(max(v, tv[degree_v]), tv[tv.shape[0] - degree_v - 1])
    span_u, span_v = knot_span(tu, degree_u, u), knot_span(tv, degree_v, v)
    basis_derivatives(tu, degree_u, span_u, u, orders, bu, work, scratch)
    basis_derivatives(tv, degree_v, span_v, v, orders, bv, work, scratch)
    # homogeneous[m] = (A, w) of derivative (du, dv): m = 0 (0,0), 1 (1,0), 2 (0,1), 3 (2,0), 4 (1,1), 5 (0,2)
    pairs = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
    count = 1 if orders == 1 else 3 if orders == 2 else 6
    for m in range(count):
        spline(bu, bv, pairs[m][0], pairs[m][1], span_u, span_v, degree_u, degree_v, nv, aw, w, homogeneous[m])
    h = homogeneous
    den = h[0, 3]
    for k in range(3):
        jet[0, k] = h[0, k] / den
    if orders == 1:
        return
    for k in range(3):
        jet[1, k] = (h[1, k] - h[1, 3] * jet[0, k]) / den
        jet[2, k] = (h[2, k] - h[2, 3] * jet[0, k]) / den
    if orders == 2:
        return
    for k in range(3):
        jet[3, k] = (h[3, k] - 2 * h[1, 3] * jet[1, k] - h[3, 3] * jet[0, k]) / den
        jet[4, k] = (h[4, k] - h[1, 3] * jet[2, k] - h[2, 3] * jet[1, k] - h[4, 3] * jet[0, k]) / den
        jet[5, k] = (h[5, k] - 2 * h[2, 3] * jet[2, k] - h[5, 3] * jet[0, k]) / den


@kernel(inline=True)
def wrap(x, closed):
    """keep_in_domain for one parameter: modulo 1 in a closed direction, clipped otherwise."""
    return np.mod(x, 1.0) if closed else min(max(x, 0.0), 1.0)


@kernel(inline=True)
def distance2(jet, point):
    d0, d1, d2 = jet[0, 0] - point[0], jet[0, 1] - point[1], jet[0, 2] - point[2]
    return (d0 * d0 + d1 * d1) + d2 * d2


@kernel(inline=True)
def dot(a, b):
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


@kernel(inline=True)
def newton_step(jet, point, u, v, closed_u, closed_v, residual, step):
    """step[0:2] = the bounded Newton step of ``foot_point_step`` for one point."""
    for k in range(3):
        residual[k] = jet[0, k] - point[k]
    su, sv, r = jet[1], jet[2], residual
    g0, g1 = dot(su, r), dot(sv, r)
    gauss0, gauss1, gauss2 = dot(su, su), dot(su, sv), dot(sv, sv)
    newton0, newton1, newton2 = gauss0 + dot(r, jet[3]), gauss1 + dot(r, jet[4]), gauss2 + dot(r, jet[5])
    if newton0 > 0 and newton0 * newton2 - newton1 * newton1 > 0:
        h0, h1, h2 = newton0, newton1, newton2
    else:
        h0, h1, h2 = gauss0, gauss1, gauss2
    shift = 1e-12 * (h0 + h2) + 1e-300
    h0 += shift
    h2 += shift
    held_u = not closed_u and ((u <= 0.0 and g0 > 0) or (u >= 1.0 and g0 < 0))
    held_v = not closed_v and ((v <= 0.0 and g1 > 0) or (v >= 1.0 and g1 < 0))
    step[0], step[1] = 0.0, 0.0
    if not held_u and not held_v:
        det = h0 * h2 - h1 * h1
        if not abs(det) > 1e-300:
            det = 1e-300
        step[0] = -(h2 * g0 - h1 * g1) / det
        step[1] = -(h0 * g1 - h1 * g0) / det
    elif not held_u:
        step[0] = -g0 / h0
    elif not held_v:
        step[1] = -g1 / h2


@kernel
def foot_points(tu, tv, degree_u, degree_v, nv, aw, w, closed_u, closed_v, points, uv, iterations,
                halvings, tolerance, out_uv, out_dist):
    """``newton_foot_points`` for every point in turn: out_uv (N, 2), out_dist (N,)."""
    size = max(degree_u, degree_v) + 1
    bu, bv = np.empty((3, degree_u + 1)), np.empty((3, degree_v + 1))
    work, scratch = np.empty((3, size)), np.empty(size)
    homogeneous, jet, trial_jet = np.empty((6, 4)), np.empty((6, 3)), np.empty((6, 3))
    residual, step = np.empty(3), np.empty(2)
    for i in range(points.shape[0]):
        point = points[i]
        u, v = wrap(uv[i, 0], closed_u), wrap(uv[i, 1], closed_v)
        # the first step's derivatives give the start's distance too (S is the same bits either way)
        surface_jet(tu, tv, degree_u, degree_v, nv, aw, w, u, v, 3 if iterations > 0 else 1, bu, bv, work, scratch,
                    homogeneous, jet)
        dist2 = distance2(jet, point)
        for iteration in range(iterations):
            if iteration > 0:
                surface_jet(tu, tv, degree_u, degree_v, nv, aw, w, u, v, 3, bu, bv, work, scratch, homogeneous, jet)
            newton_step(jet, point, u, v, closed_u, closed_v, residual, step)
            moved = False
            for halving in range(halvings):
                scale = 0.5 ** halving
                trial_u, trial_v = wrap(u + scale * step[0], closed_u), wrap(v + scale * step[1], closed_v)
                if trial_u == u and trial_v == v:
                    break  # the step is below rounding: so is every halving, none can bring the point closer
                surface_jet(tu, tv, degree_u, degree_v, nv, aw, w, trial_u, trial_v, 1, bu, bv, work, scratch,
                            homogeneous, trial_jet)
                trial_d2 = distance2(trial_jet, point)
                if trial_d2 < dist2:
                    u, v, dist2, moved = trial_u, trial_v, trial_d2, True
                    break
            if not moved or not max(abs(step[0]), abs(step[1])) > tolerance:
                break
        out_uv[i, 0], out_uv[i, 1], out_dist[i] = u, v, np.sqrt(dist2)

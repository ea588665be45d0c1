"""Finish the kept surface: parameter correction (``polish``: least squares alternated
with foot points), the smoothing re-chosen by leave-one-out and a second polish
(``finishing``); the joint Levenberg-Marquardt refinement and its acceptance
(``refine``); the footprint and trims (``footprint``); the self-checks (``self_checks``).
"""

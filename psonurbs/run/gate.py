"""The regression gate: bounds on a fit's RMSE (``--max-rmse``, ``--max-rmse-rel``), and
optionally its self-checks (``--fail-suspect``) and its tolerance (``--fail-unmet``)."""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Gate"]


@dataclass(frozen=True)
class Gate:
    """Regression bounds: RMSE in cloud units, and relative to the bounding-box diagonal;
    with ``fail_suspect``, a fit that failed a self-check (``warnings``) fails the gate too; with
    ``fail_unmet``, a fit to a tolerance that it does not meet (``unmet``: the reason)."""

    max_rmse: float | None = None
    max_rmse_rel: float | None = None
    fail_suspect: bool = False
    fail_unmet: bool = False

    def check(self, metrics: dict, warnings: list[str] = (), unmet: str = "") -> str:
        """'' when the fit passes, else the reason (for the row's message)."""
        reasons = []
        if self.fail_suspect and warnings:
            reasons.append(f"suspect fit ({len(warnings)} self-check{'s' if len(warnings) > 1 else ''} failed) "
                           "with --fail-suspect")
        if self.fail_unmet and unmet:
            reasons.append(f"{unmet} with --fail-unmet")
        rmse, rel = metrics.get("rmse", math.nan), metrics.get("rmse_relative", math.nan)
        if self.max_rmse is not None and not rmse <= self.max_rmse:
            reasons.append(f"rmse {rmse:.3e} > --max-rmse {self.max_rmse:g}")
        if self.max_rmse_rel is not None and not rel <= self.max_rmse_rel:
            reasons.append(f"relative rmse {rel:.3e} > --max-rmse-rel {self.max_rmse_rel:g}")
        return "; ".join(reasons)

    def as_dict(self) -> dict:
        out = {"max_rmse": self.max_rmse, "max_rmse_rel": self.max_rmse_rel, "fail_suspect": self.fail_suspect}
        if self.fail_unmet:  # only when set: a run without tolerances writes the summary it always wrote
            out["fail_unmet"] = True
        return out

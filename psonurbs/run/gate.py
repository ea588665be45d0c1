"""The regression gate: bounds on a fit's RMSE (``--max-rmse``, ``--max-rmse-rel``)."""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Gate"]


@dataclass(frozen=True)
class Gate:
    """Regression bounds: RMSE in cloud units, and relative to the bounding-box diagonal."""

    max_rmse: float | None = None
    max_rmse_rel: float | None = None

    def check(self, metrics: dict) -> str:
        """'' when the fit passes, else the reason (for the row's message)."""
        reasons = []
        rmse, rel = metrics.get("rmse", math.nan), metrics.get("rmse_relative", math.nan)
        if self.max_rmse is not None and not rmse <= self.max_rmse:
            reasons.append(f"rmse {rmse:.3e} > --max-rmse {self.max_rmse:g}")
        if self.max_rmse_rel is not None and not rel <= self.max_rmse_rel:
            reasons.append(f"relative rmse {rel:.3e} > --max-rmse-rel {self.max_rmse_rel:g}")
        return "; ".join(reasons)

    def as_dict(self) -> dict:
        return {"max_rmse": self.max_rmse, "max_rmse_rel": self.max_rmse_rel}

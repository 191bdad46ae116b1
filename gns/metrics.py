"""Deposit measures of a column collapse, the same for a GNS rollout and an MPM run.

Front and height are high quantiles rather than maxima, so that a few particles thrown
ahead of the deposit do not set them; both are in m from the back wall (x = 0) and the floor
(z = 0). The displacement range is that of the displacement magnitude |x(t) - x(0)| over
the particles at the final frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

FRONT_QUANTILE = 0.99
HEIGHT_QUANTILE = 0.99


@dataclass(frozen=True)
class Deposit:
    runout_m: float  # FRONT_QUANTILE of x at the final frame
    height_m: float  # HEIGHT_QUANTILE of z at the final frame
    displacement_min_m: float
    displacement_max_m: float

    def as_dict(self) -> dict:
        return asdict(self)


def deposit(positions: np.ndarray) -> Deposit:
    """positions [frames, n, 3] (m) of one run."""
    last = positions[-1].astype(np.float64)
    disp = np.linalg.norm(last - positions[0], axis=1)
    return Deposit(float(np.quantile(last[:, 0], FRONT_QUANTILE)),
                   float(np.quantile(last[:, 2], HEIGHT_QUANTILE)),
                   float(disp.min()), float(disp.max()))


def signed_relative_error(a: float, b: float) -> float:
    """(a - b) / b, a fraction (> 0: a exceeds b); inf when b is 0."""
    return (a - b) / b if b else float("inf")


def relative_errors(pred: Deposit, ref: Deposit) -> dict:
    """Relative errors (fractions) of runout, height and displacement range vs ref."""
    def rel(a: float, b: float) -> float:
        return abs(signed_relative_error(a, b))
    return {"runout": rel(pred.runout_m, ref.runout_m), "height": rel(pred.height_m, ref.height_m),
            "displacement_range": rel(pred.displacement_max_m - pred.displacement_min_m,
                                      ref.displacement_max_m - ref.displacement_min_m)}


def mean_position_error(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean over frames and particles of |pred - ref| (m); same particles, same frames."""
    frames = min(len(pred), len(ref))
    return float(np.linalg.norm(pred[:frames] - ref[:frames], axis=2).mean())

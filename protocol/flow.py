"""How a run's motion is read from the speed histograms of its Stats messages: one rule for
the oracle's analysis (gns.events), its score (minority score) and the live view
(render_server.live).

A frame's speed scale is the SPEED_QUANTILE of its particle speeds; a particle moves when
faster than MOVING_SPEED_FRACTION of the run's peak speed scale.
"""

from __future__ import annotations

import numpy as np

from minority.protocol.messages import SPEED_EDGES_M_S

MOVING_SPEED_FRACTION = 0.05  # a particle moves when faster than this fraction of the peak speed
SPEED_QUANTILE = 0.95  # the speed scale of a frame
_EDGES = np.asarray(SPEED_EDGES_M_S)
_LO = np.r_[_EDGES[0] * 0.1, _EDGES]  # bin i spans [_LO[i], _HI[i]) m/s
_HI = np.r_[_EDGES, _EDGES[-1] * 10]


def histogram_quantile(hist: np.ndarray, q: float = SPEED_QUANTILE) -> np.ndarray:
    """Per row of hist [k, SPEED_BINS] the q-quantile speed (m/s), log-interpolated within
    its bin; the lowest bin (below 1e-4 m/s) and an empty row read as rest (0)."""
    hist = np.asarray(hist)
    cum = np.cumsum(hist, axis=1)
    target = q * cum[:, -1]
    i = np.minimum((cum < target[:, None]).sum(axis=1), hist.shape[1] - 1)
    rows = np.arange(len(hist))
    below = np.where(i > 0, cum[rows, np.maximum(i - 1, 0)], 0)
    frac = (target - below) / np.maximum(hist[rows, i], 1)
    return np.where((i > 0) & (cum[:, -1] > 0), _LO[i] * (_HI[i] / _LO[i]) ** frac, 0.0)


def moving_count(hist: np.ndarray, threshold_m_s: float) -> np.ndarray:
    """Particles per row of hist [k, SPEED_BINS] faster than the threshold (m/s): the bins
    whose lower edge is at or above it."""
    lower = np.r_[0.0, _EDGES]
    return np.asarray(hist)[:, lower >= threshold_m_s].sum(axis=1)

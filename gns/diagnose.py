"""Teacher-forced acceleration balance: where a checkpoint's one-frame predictions go wrong.

For every frame f of a band the model gets the run's own last C+1 frames (no rollout
feedback) and predicts the acceleration of frame f + 1; the predicted and the run's
accelerations along the flow (x, m/frame^2) are summed over the particles of a region and
over the band. Their ratio is the momentum the model adds (or removes) per unit the run
does: below 1 in a band where the region accelerates, it starts too slowly; above 1 where
it decelerates, it brakes too hard. A rollout compounds these one-frame errors, so a ratio
off by 20 % over a band moves the deposit without any divergence to see.

Regions, from each input frame's positions: the whole column; depth below the local free
surface (the highest particle within the same (x, y) bin of one connectivity radius);
distance to the nearer side wall (y faces); the leading 20 % in x and the rest.
"""

from __future__ import annotations

import numpy as np
import torch

from minority.gns.dataset import Trajectory
from minority.gns.graph import radius_graph

DEPTH_BANDS_M = ((0.0, 0.03), (0.03, 0.08), (0.08, 0.145), (0.145, np.inf))
WALL_BANDS_M = ((0.0, 0.03), (0.03, 0.145), (0.145, np.inf))
FRONT_QUANTILE = 0.8  # particles beyond this quantile of x are "front"


def depth_below_surface(pos: np.ndarray, bin_m: float) -> np.ndarray:
    """[n] m: for each particle of pos [n, 3] (m), the height of the highest particle in its
    (x, y) bin of edge bin_m above it (0 for the top particle of a bin)."""
    ij = np.floor(pos[:, :2] / bin_m).astype(np.int64)
    _, inv = np.unique(ij, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    top = np.full(inv.max() + 1, -np.inf)
    np.maximum.at(top, inv, pos[:, 2])
    return top[inv] - pos[:, 2]


def regions(pos: np.ndarray, bounds_m: np.ndarray, bin_m: float) -> dict[str, np.ndarray]:
    """Boolean masks [n] of the regions named in the module docstring."""
    depth = depth_below_surface(pos, bin_m)
    wall = np.minimum(pos[:, 1] - bounds_m[1, 0], bounds_m[1, 1] - pos[:, 1])
    front = pos[:, 0] > np.quantile(pos[:, 0], FRONT_QUANTILE)
    out = {"all": np.ones(len(pos), bool), "front": front, "behind front": ~front}
    for lo, hi in DEPTH_BANDS_M:
        out[f"depth {lo:g}-{hi:g} m"] = (depth >= lo) & (depth < hi)
    for lo, hi in WALL_BANDS_M:
        out[f"side wall {lo:g}-{hi:g} m"] = (wall >= lo) & (wall < hi)
    return out


def predicted_acceleration(model, window: np.ndarray, friction_deg: float,
                           bounds_m: np.ndarray) -> np.ndarray:
    """[n, 3] m/frame^2 predicted for the frame after window [C+1, n, 3] (m)."""
    x = np.ascontiguousarray(np.transpose(window, (1, 0, 2)), dtype=np.float32)
    s, r = radius_graph(x[:, -1], model.radius)
    with torch.no_grad():
        return model.acceleration(torch.from_numpy(x), torch.full((len(x),), float(friction_deg)),
                                  torch.as_tensor(bounds_m, dtype=torch.float32),
                                  torch.from_numpy(s), torch.from_numpy(r)).numpy()


def balance(model, traj: Trajectory, bands: list[tuple[int, int]]) -> list[dict]:
    """One row per (band, region): frames [f0, f1) are the last input frames (f0 >= C);
    pred_m and true_m are the summed x accelerations per frame of the band (m/frame^2
    summed over particles), ratio pred_m / true_m, particle_frames the count behind it."""
    c = model.config.input_velocities
    x = traj.positions
    rows = []
    for f0, f1 in bands:
        if f0 < c or f1 > len(x) - 1 or f1 <= f0:
            raise ValueError(f"band {f0}:{f1} must lie within frames {c}..{len(x) - 1} "
                             f"of {traj.name} (the first C={c} frames are input only)")
        sums: dict[str, list[float]] = {}
        for f in range(f0, f1):
            pred = predicted_acceleration(model, x[f - c:f + 1], traj.friction_angle_deg,
                                          traj.bounds_m)[:, 0].astype(np.float64)
            true = x[f + 1, :, 0].astype(np.float64) - 2 * x[f, :, 0] + x[f - 1, :, 0]
            for name, mask in regions(x[f].astype(np.float64), traj.bounds_m,
                                      model.radius).items():
                s = sums.setdefault(name, [0.0, 0.0, 0])
                s[0] += pred[mask].sum()
                s[1] += true[mask].sum()
                s[2] += int(mask.sum())
        for name, (p, t, count) in sums.items():
            rows.append({"scene": traj.name, "frames": [f0, f1], "region": name,
                         "pred_m": p / (f1 - f0), "true_m": t / (f1 - f0),
                         "ratio": p / t if t else None, "particle_frames": count})
    return rows

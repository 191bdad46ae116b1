"""Rollout: the GNS predicts a run frame by frame from its first C+1 frames.

Walls are rigid, as in the MPM (which clamps a particle advected out of the domain back to
the face): a predicted position slightly outside the domain is clamped to it and counted.
A rollout stops with `RolloutError` naming the frame when positions turn non-finite or a
particle leaves the domain by more than `ESCAPE_RADII` connectivity radii in one frame (no
physical step moves that far: the fastest particles of the training runs move a seventh of
a radius per frame).
"""

from __future__ import annotations

import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from minority.gns.graph import radius_graph
from minority.gns.metrics import deposit, relative_errors, signed_relative_error

ESCAPE_RADII = 1.0  # connectivity radii outside the domain that count as leaving it


class RolloutError(RuntimeError):
    """The rollout diverged; the message names the frame. `frame` is that frame and
    `positions` [frame, n, 3] the frames before it."""

    def __init__(self, message: str, frame: int, positions: np.ndarray) -> None:
        super().__init__(message)
        self.frame = frame
        self.positions = positions


@dataclass
class InitialState:
    positions: np.ndarray  # [C+1, n, 3] float64, m (oldest first)
    friction_deg: float
    bounds_m: np.ndarray  # [3, 2]
    name: str
    duration_s: float  # the scene's simulated time, s


def _lattice(lo, hi, s: float) -> np.ndarray:
    """Points (i + 1/2) s inside [lo, hi] per axis, [m, 3] (the MPM seeding lattice)."""
    axes = []
    for a in range(3):
        c = (np.arange(int(np.floor(lo[a] / s + 1e-9)), int(np.ceil(hi[a] / s - 1e-9))) + 0.5) * s
        axes.append(c[(c >= lo[a]) & (c <= hi[a])])
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


def initial_state(scene_toml: str | Path, spacing_m: float, frame_interval_s: float,
                  history: int) -> InitialState:
    """Seed a scene's bodies (TOML as `minority sim` reads it) at the model's particle
    spacing; the history frames move back along each body's initial velocity."""
    path = Path(scene_toml)
    try:
        raw = tomllib.loads(path.read_text())
        size = np.array(raw["domain"]["size_m"], np.float64)
        friction = float(raw["material"]["friction_angle_deg"])
        duration = float(raw["time"]["duration_s"])
        bodies = raw["body"]
    except (OSError, tomllib.TOMLDecodeError, KeyError) as exc:
        raise ValueError(f"{path}: cannot read the scene ({exc!r})") from None
    pts, vel, taken = [], [], set()
    for b in bodies:
        if b.get("shape", "box") == "box":
            p = _lattice(b["lo_m"], b["hi_m"], spacing_m)
        else:
            c, r = np.array(b["center_m"], np.float64), float(b["radius_m"])
            p = _lattice(c - [r, r, 0.0], c + [r, r, float(b["height_m"])], spacing_m)
            p = p[(p[:, 0] - c[0]) ** 2 + (p[:, 1] - c[1]) ** 2 <= r * r]
        keys = [tuple(k) for k in np.rint(p / spacing_m - 0.5).astype(np.int64)]
        keep = np.array([k not in taken for k in keys], bool)
        taken.update(k for k, ok in zip(keys, keep, strict=False) if ok)
        pts.append(p[keep])
        vel.append(np.broadcast_to(np.array(b.get("velocity_m_s", [0.0, 0.0, 0.0])), p[keep].shape))
    x, v = np.concatenate(pts), np.concatenate(vel) * frame_interval_s
    if len(x) == 0:
        raise ValueError(f"{path}: no particles at spacing {spacing_m} m")
    frames = np.stack([x - (history - k) * v for k in range(history + 1)])
    bounds = np.stack([np.zeros(3), size], axis=1)
    return InitialState(frames, friction, bounds, raw.get("name", path.stem), duration)


def rollout(model, positions: np.ndarray, friction_deg: float, bounds_m: np.ndarray,
            frames: int, *, device: str = "cpu", progress: bool = False,
            log=None) -> tuple[np.ndarray, dict]:
    """Predict `frames` frames after the C+1 given ones ([C+1, n, 3], m).

    Returns all frames [C+1+frames, n, 3] float32 and {graph_s, model_s, clamped} (clamped:
    particle positions put back on a domain face, summed over frames)."""
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    c1 = model.config.input_velocities + 1
    if positions.shape[0] < c1:
        raise ValueError(f"rollout needs {c1} initial frames, got {positions.shape[0]}")
    n = positions.shape[1]
    out = np.empty((c1 + frames, n, 3), np.float32)
    out[:c1] = positions[-c1:]
    window = torch.as_tensor(np.transpose(positions[-c1:], (1, 0, 2)), dtype=torch.float32,
                             device=device)
    fr = torch.full((n,), float(friction_deg), device=device)
    bounds = torch.as_tensor(bounds_m, dtype=torch.float32, device=device)
    lo, hi = np.asarray(bounds_m)[:, 0], np.asarray(bounds_m)[:, 1]
    tol = ESCAPE_RADII * model.radius
    lo_t, hi_t = bounds[:, 0], bounds[:, 1]
    timing = {"graph_s": 0.0, "model_s": 0.0, "clamped": 0}
    t_print = time.perf_counter()
    with torch.no_grad():
        for k in range(frames):
            t0 = time.perf_counter()
            last = window[:, -1].cpu().numpy()
            s, r = radius_graph(last, model.radius)
            s_t = torch.as_tensor(s, device=device)
            r_t = torch.as_tensor(r, device=device)
            t1 = time.perf_counter()
            nxt = model.next_positions(window, fr, bounds, s_t, r_t)
            x = nxt.cpu().numpy()
            frame = c1 + k
            if not np.isfinite(x).all():
                raise RolloutError(f"rollout diverged at frame {frame}: non-finite positions",
                                   frame, out[:frame])
            out_lo, out_hi = (x < lo - tol).any(axis=1), (x > hi + tol).any(axis=1)
            if out_lo.any() or out_hi.any():
                i = int(np.flatnonzero(out_lo | out_hi)[0])
                raise RolloutError(f"rollout diverged at frame {frame}: particle {i} left the "
                                   f"domain at {x[i].round(4).tolist()} m", frame, out[:frame])
            outside = (x < lo) | (x > hi)
            if outside.any():
                timing["clamped"] += int(outside.any(axis=1).sum())
                nxt = torch.minimum(torch.maximum(nxt, lo_t), hi_t)
                x = nxt.cpu().numpy()
            window = torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)
            timing["graph_s"] += t1 - t0
            timing["model_s"] += time.perf_counter() - t1
            out[frame] = x
            if progress and time.perf_counter() - t_print > 2.0:
                print(f"rollout: frame {frame}/{c1 + frames - 1}", file=log, flush=True)
                t_print = time.perf_counter()
    return out, timing


def rollout_error(model, traj, frames: int, device: str = "cpu") -> dict:
    """A validation rollout of up to `frames` frames against the trajectory: error_m (mean
    position error, m), frames (predicted; fewer when the rollout diverged) and, when it
    reached the trajectory's last frame, the relative deposit errors (fractions) runout and
    displacement_range of gns.metrics, runout_signed (> 0: the front runs too far) and
    height_signed (< 0: the deposit is too flat); None otherwise)."""
    c1 = model.config.input_velocities + 1
    frames = min(frames, traj.positions.shape[0] - c1)
    try:
        pred, _ = rollout(model, traj.positions[:c1].astype(np.float64), traj.friction_angle_deg,
                          traj.bounds_m, frames, device=device)
    except RolloutError as exc:
        pred = exc.positions
    done = len(pred) - c1
    true = traj.positions[:len(pred)]
    err = float(np.linalg.norm(pred[c1:] - true[c1:], axis=2).mean()) if done else float("inf")
    rel, signed, height = {}, None, None
    if len(pred) == traj.positions.shape[0]:
        got, ref = deposit(pred), deposit(traj.positions)
        rel = relative_errors(got, ref)
        signed = signed_relative_error(got.runout_m, ref.runout_m)
        height = signed_relative_error(got.height_m, ref.height_m)
    return {"error_m": err, "frames": done, "runout": rel.get("runout"),
            "displacement_range": rel.get("displacement_range"), "runout_signed": signed,
            "height_signed": height}

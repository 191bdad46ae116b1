"""What a predicted run does and when: events, windows, extents (the oracle's analysis).

Works on any trajectory [frames, n, 3] (m) with its frame interval (s): a GNS rollout, or
an MPM run when the prediction is scored. Speeds are in m/s; the event series use centered
differences, so that a frame's speed is the speed at its time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minority.protocol.flow import MOVING_SPEED_FRACTION, SPEED_QUANTILE  # noqa: F401 - re-exported

ONSET_FRACTION = 0.05  # failure onset: the speed scale first exceeds this fraction of its peak
REST_FRACTION = 0.01  # end of runout: kinetic energy back below this fraction of its peak
FAST_FRACTION = 0.5  # the main runout phase: the speed scale above this fraction of its peak


@dataclass(frozen=True)
class Events:
    onset_s: float  # failure initiation
    peak_s: float  # fastest motion (kinetic-energy peak)
    runout_end_s: float  # back to rest
    duration_s: float  # the trajectory's last time
    peak_speed_m_s: float  # speed scale (SPEED_QUANTILE) at the peak
    speed_scale_m_s: np.ndarray  # [frames] SPEED_QUANTILE of the particle speeds
    kinetic_m2_s2: np.ndarray  # [frames] mean squared speed (specific kinetic energy x 2)


def speeds(positions: np.ndarray, frame_interval_s: float, centered: bool = False) -> np.ndarray:
    """[frames, n] particle speed (m/s) from positions [frames, n, 3] (m).

    Backward differences by default (frame 0: 0): the mean speed over the frame before, i.e.
    the speed half a frame before the frame's time. `centered`: (x[k+1] - x[k-1]) / 2 dt, the
    speed at the frame's own time (one-sided at the ends), as a run's instantaneous particle
    velocities give it; event times from backward differences come out half a frame late.
    """
    x = positions.astype(np.float64)
    if centered and len(x) > 1:
        return np.linalg.norm(np.gradient(x, frame_interval_s, axis=0), axis=2)
    s = np.zeros(positions.shape[:2])
    s[1:] = np.linalg.norm(np.diff(x, axis=0), axis=2) / frame_interval_s
    return s


def find_events(positions: np.ndarray, frame_interval_s: float) -> Events:
    """Events of a trajectory, from the speed at each frame's time (centered differences)."""
    sp = speeds(positions, frame_interval_s, centered=True)
    return events_from_series(np.arange(len(sp)) * frame_interval_s,
                              np.quantile(sp, SPEED_QUANTILE, axis=1), (sp * sp).mean(axis=1))


def events_from_series(time_s: np.ndarray, speed_scale_m_s: np.ndarray,
                       kinetic_m2_s2: np.ndarray) -> Events:
    """Events from per-frame series [frames]: times (s), speed scale (m/s) and mean squared
    speed (m^2/s^2); the same rules for a rollout and for a run's in situ statistics."""
    t, scale, ke = (np.asarray(a, dtype=np.float64) for a in (time_s, speed_scale_m_s,
                                                              kinetic_m2_s2))
    above = np.flatnonzero(scale >= ONSET_FRACTION * scale.max())
    onset = int(above[0]) if len(above) else 0
    # the kinetic-energy peak of the flow: at or after the onset (a few particles flung
    # before the bulk moves can carry an earlier, larger spike)
    peak = onset + int(np.argmax(ke[onset:]))
    after = np.flatnonzero(ke[peak:] < REST_FRACTION * ke[peak])
    end = peak + int(after[0]) if len(after) else len(ke) - 1
    return Events(float(t[onset]), float(t[peak]), float(t[end]), float(t[-1]),
                  float(scale[peak]), scale, ke)


def fast_windows(time_s: np.ndarray, speed_scale_m_s: np.ndarray,
                 fraction: float = FAST_FRACTION) -> list[tuple[float, float]]:
    """The intervals [t0, t1] (s) where the speed scale is at least `fraction` of its peak:
    the main runout phase, where the critical frames are."""
    t = np.asarray(time_s, dtype=np.float64)
    fast = np.asarray(speed_scale_m_s) >= fraction * np.max(speed_scale_m_s)
    edges = np.flatnonzero(np.diff(np.r_[0, fast.astype(np.int8), 0]))
    return [(float(t[a]), float(t[b - 1])) for a, b in zip(edges[::2], edges[1::2], strict=True)]


EVENT_NAMES = ("failure_onset", "runout_start", "peak_motion", "runout_end")


def fast_start_s(e: Events, frame_interval_s: float) -> float:
    """When the predicted runout starts, s: the first fast window's start (speed scale at
    least half its peak), after the onset and no later than the peak; the peak when the run
    has no fast window."""
    t = np.arange(len(e.speed_scale_m_s)) * frame_interval_s
    fast = fast_windows(t, e.speed_scale_m_s)
    return min(max(fast[0][0], e.onset_s + frame_interval_s), e.peak_s) if fast else e.peak_s


def event_times(e: Events, frame_interval_s: float) -> dict[str, float]:
    """The events a spec names (EVENT_NAMES) and their times, s, as the oracle states them:
    the runout start is the runout window's first frame after its one-frame pad."""
    dt = frame_interval_s
    return {"failure_onset": e.onset_s,
            "runout_start": max(0.0, fast_start_s(e, dt) - dt) + dt,
            "peak_motion": e.peak_s, "runout_end": e.runout_end_s}


def _frames(positions: np.ndarray, frame_interval_s: float, t0: float, t1: float) -> slice:
    """The frames whose times lie in [t0, t1] (rounded outwards)."""
    k0 = max(int(np.floor(t0 / frame_interval_s)), 0)
    k1 = min(int(np.ceil(t1 / frame_interval_s)), len(positions) - 1)
    return slice(k0, k1 + 1)


def moving_points(positions: np.ndarray, frame_interval_s: float, t0: float, t1: float,
                  speed_threshold_m_s: float) -> np.ndarray | None:
    """[k, 3] every position (m) in [t0, t1] of the particles that move faster than the
    threshold at any frame of it; None when nothing moves."""
    w = _frames(positions, frame_interval_s, t0, t1)
    first = max(w.start - 1, 0)  # a frame's speed needs the frame before it
    sp = speeds(positions[first:w.stop], frame_interval_s)[w.start - first:]
    moving = (sp > speed_threshold_m_s).any(axis=0)
    if not moving.any():
        return None
    return positions[w, moving].reshape(-1, 3)


def moving_extent(positions: np.ndarray, frame_interval_s: float, t0: float, t1: float,
                  speed_threshold_m_s: float) -> np.ndarray | None:
    """[3, 2] bounds (m) of the particles that move faster than the threshold at any frame in
    [t0, t1], over all their positions in the window; None when nothing moves."""
    pts = moving_points(positions, frame_interval_s, t0, t1, speed_threshold_m_s)
    return None if pts is None else np.stack([pts.min(axis=0), pts.max(axis=0)], axis=1)


def extent(positions: np.ndarray, frame_interval_s: float, t0: float, t1: float) -> np.ndarray:
    """[3, 2] bounds (m) of every particle over the frames in [t0, t1]."""
    pts = positions[_frames(positions, frame_interval_s, t0, t1)].reshape(-1, 3)
    return np.stack([pts.min(axis=0), pts.max(axis=0)], axis=1)


def displacement_range(positions: np.ndarray) -> tuple[float, float]:
    """(min, max) of |x(t) - x(0)| over all frames and particles, m."""
    d = np.linalg.norm(positions - positions[0], axis=2)
    return float(d.min()), float(d.max())

"""Oracle analysis on a synthetic run with known events and extent."""

import numpy as np
import pytest

from minority.gns.events import displacement_range, extent, find_events, moving_extent

DT = 0.01


def _synthetic(n=400, frames=101, start=0.10, stop=0.50, seed=0):
    """Half the particles slide +x at a smooth speed bump between start and stop (s); the
    other half never move."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0, 0.1, (n, 3))
    t = np.arange(frames) * DT
    phase = np.clip((t - start) / (stop - start), 0, 1)
    travel = 0.3 * (phase - np.sin(2 * np.pi * phase) / (2 * np.pi))  # speed ~ 1 - cos
    pos = np.repeat(x0[None], frames, axis=0)
    pos[:, : n // 2, 0] += travel[:, None]
    return pos, x0


def test_events_found_within_tolerance():
    pos, _ = _synthetic()
    e = find_events(pos, DT)
    assert e.peak_s == pytest.approx(0.30, abs=0.02)  # speed peaks mid-way
    assert 0.10 <= e.onset_s <= 0.16  # 5% of the peak speed is reached soon after start
    assert 0.44 <= e.runout_end_s <= 0.50  # kinetic energy below 1% of its peak before stop
    assert e.peak_speed_m_s == pytest.approx(0.3 * 2 / 0.4, rel=0.02)  # 2 x mean speed


def test_moving_extent_and_ranges():
    pos, x0 = _synthetic()
    e = find_events(pos, DT)
    box = moving_extent(pos, DT, e.onset_s, e.runout_end_s, 0.05 * e.peak_speed_m_s)
    movers = x0[:200]
    np.testing.assert_allclose(box[:, 0], movers.min(axis=0), atol=0.02)
    assert box[0, 1] == pytest.approx(movers[:, 0].max() + 0.3, abs=0.02)
    assert moving_extent(pos, DT, 0.0, 0.05, 0.01) is None  # nothing moves before the start
    full = extent(pos, DT, 0.0, 1.0)
    np.testing.assert_allclose(full[:, 0], pos.reshape(-1, 3).min(axis=0))
    lo, hi = displacement_range(pos)
    assert lo == 0.0 and hi == pytest.approx(0.3, abs=1e-9)


def test_fast_windows_cover_the_speed_bump():
    from minority.gns.events import fast_windows, speeds

    pos, _ = _synthetic()
    scale = np.quantile(speeds(pos, DT), 0.95, axis=1)
    t = np.arange(len(scale)) * DT
    (t0, t1), = fast_windows(t, scale)
    # speed ~ 1 - cos(2 pi phase) is above half its peak for the middle half of [0.1, 0.5]
    assert t0 == pytest.approx(0.20, abs=0.015) and t1 == pytest.approx(0.40, abs=0.015)
    steps = np.array([1.0, 0.0, 1.0, 1.0, 0.0, 0.2])
    assert fast_windows(t[:6], steps) == [(0.0, 0.0), (0.02, 0.03)]


def test_event_speeds_are_taken_at_the_frame_times():
    """A run's in situ statistics use instantaneous velocities; a backward difference is the
    speed half a frame earlier, so the event series use centered differences."""
    from minority.gns.events import speeds

    t = np.arange(41) * DT
    accel = 2.0  # m/s^2, from rest
    pos = np.zeros((41, 3, 3))
    pos[:, :, 0] = 0.5 * accel * t[:, None] ** 2
    np.testing.assert_allclose(speeds(pos, DT, centered=True)[1:-1, 0], accel * t[1:-1])
    np.testing.assert_allclose(speeds(pos, DT)[1:, 0], accel * (t[1:] - DT / 2))
    # the onset (5 % of the peak speed scale, 0.04 m/s at t = 0.02 s) is found at its frame
    assert find_events(pos, DT).onset_s == pytest.approx(0.02)

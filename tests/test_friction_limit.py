"""bench.friction_limit's reading of a run: the peak, the fast phase and the deposit."""

import h5py
import numpy as np
import pytest

from bench.friction_limit import cases, measure


def write_run(path, speed_of_t, n=100):
    """A run whose particles all move along x at speed_of_t(t) m/s, a frame every 5 ms."""
    t = np.arange(0, 1.0001, 0.005)
    v = np.array([speed_of_t(s) for s in t])
    vel = np.zeros((len(t), n, 3), np.float32)
    vel[:, :, 0] = v[:, None]
    disp = np.zeros_like(vel)
    disp[:, :, 0] = np.cumsum(v * 0.005)[:, None]
    with h5py.File(path, "w") as f:
        f["time"], f["velocities"], f["displacements"] = t, vel, disp
        f["positions"] = disp


def test_a_failure_reads_its_peak_and_fast_phase_and_a_settling_reads_none(tmp_path):
    write_run(tmp_path / "fails.h5", lambda t: max(0.0, 1.0 - abs(t - 0.3) / 0.2))
    m = measure(tmp_path / "fails.h5")
    assert m["peak_s"] == pytest.approx(0.3) and m["peak_speed_m_s"] == pytest.approx(1.0)
    assert m["fast_from_s"] == pytest.approx(0.2)  # half the peak
    assert m["max_displacement_m"] == pytest.approx(0.2, rel=0.03)  # the triangle's area
    assert m["particles"] == 100
    write_run(tmp_path / "stands.h5", lambda t: max(0.0, 0.04 - abs(t - 0.02)))
    m = measure(tmp_path / "stands.h5")
    assert m["peak_s"] == pytest.approx(0.02) and m["fast_from_s"] is None


def test_the_cases_hold_every_step_at_45_deg_and_the_fine_grid_only_when_asked():
    names = [n for n, _ in cases(False)]
    assert {"friction_45_cfl0.3", "friction_45_cfl0.1", "friction_45_pic",
            "test_003_cfl0.1"} <= set(names)
    assert not any("fine" in n for n in names)
    fine = dict(cases(True))
    assert fine["friction_45_fine_cfl0.1"] == {"friction_angle_deg": 45.0,
                                               "cell_size_m": 0.008, "cfl": 0.1}

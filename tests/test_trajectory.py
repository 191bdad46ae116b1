"""The HDF5 trajectory layout (protocol.trajectory): writer and readers round trip, files in
the layout written before it had one home still read, a killed writer's partial frame is not
read, and hostile files are refused with TrajectoryError."""

import json

import h5py
import numpy as np
import pytest

from minority.protocol.trajectory import (
    FRAME_FIELDS,
    ROLLOUT_FORMAT,
    SIM_FORMAT,
    SIM_SERIES,
    UNITS,
    FrameWriter,
    TrajectoryError,
    frames_written,
    open_trajectory,
    read_rollout,
    read_sim,
    write_rollout,
)

DT = 0.01  # s between frames
BOUNDS = [[0.0, 0.4], [0.0, 0.1], [0.0, 0.2]]  # m


def falling(frames=6, n=5):
    """positions [frames, n, 3] float32, m: particles falling from rest."""
    x0 = np.random.default_rng(0).uniform(0.02, 0.08, (n, 3))
    t = np.arange(frames) * DT
    return (x0[None] - np.stack([0 * t, 0 * t, 4.905 * t * t], 1)[:, None]).astype(np.float32)


def sim_file(path, pos, phi=31.0):
    """An MPM run's file as sim.output writes it (without a Scene)."""
    frames, n, _ = pos.shape
    with FrameWriter(path, n, fmt=SIM_FORMAT, units=UNITS,
                     attrs={"output_interval_s": DT, "bounds_m": np.array(BOUNDS),
                            "particle_spacing_m": 0.01, "scene_name": "fall",
                            "scene_toml": "[domain]\nsize_m = [0.4, 0.1, 0.2]\n"},
                     particle_data={"material": np.full(n, phi, np.float32)},
                     series=SIM_SERIES) as w:
        for k in range(frames):
            v = (pos[k] - pos[max(k - 1, 0)]) / DT
            w.write_frame(k * DT, {"positions": pos[k], "velocities": v,
                                   "displacements": pos[k] - pos[0]},
                          step=10 * k, kinetic_energy=0.5 * float((v * v).sum()),
                          momentum=v.sum(axis=0))
    return w


def test_frame_writer_writes_the_layout(tmp_path):
    pos = falling()
    w = sim_file(tmp_path / "run.h5", pos)
    assert w.frames == len(pos)
    with open_trajectory(tmp_path / "run.h5") as f:
        for name in FRAME_FIELDS:
            assert f[name].shape == pos.shape and f[name].dtype == np.float32
            assert f[name].chunks == (1, *pos.shape[1:]) and f[name].maxshape[0] is None
        np.testing.assert_array_equal(f["positions"][()], pos)
        np.testing.assert_allclose(f["displacements"][()], pos - pos[0], atol=1e-7)
        np.testing.assert_allclose(f["time"][()], np.arange(len(pos)) * DT)
        assert f["time"].dtype == np.float64 and f["step"].dtype == np.int64
        assert f["momentum"].shape == (len(pos), 3) and f["kinetic_energy"][0] == 0.0
        assert f.attrs["format"] == SIM_FORMAT and f.attrs["n_particles"] == pos.shape[1]
        assert json.loads(f.attrs["units"])["velocities"] == "m/s"
    assert frames_written(tmp_path / "run.h5") == len(pos)
    assert frames_written(tmp_path / "missing.h5") == 0


def test_read_sim_takes_every_stride_th_frame(tmp_path):
    pos = falling(frames=7)
    sim_file(tmp_path / "run.h5", pos)
    got, attrs = read_sim(tmp_path / "run.h5", stride=2)
    np.testing.assert_array_equal(got, pos[::2])
    assert attrs["friction_angle_deg"] == 31.0 and attrs["output_interval_s"] == DT
    assert attrs["scene_name"] == "fall" and attrs["particle_spacing_m"] == 0.01
    np.testing.assert_array_equal(attrs["bounds_m"], BOUNDS)


def test_rollout_round_trip(tmp_path):
    pos = falling()
    vel = np.zeros_like(pos)
    vel[1:] = (pos[1:] - pos[:-1]) / DT
    write_rollout(tmp_path / "sub" / "r.h5", pos, vel, DT,
                  attrs={"bounds_m": BOUNDS, "scene": "fall", "wall_s": 1.5})
    r = read_rollout(tmp_path / "sub" / "r.h5")
    assert r["format"] == ROLLOUT_FORMAT and r["frame_interval_s"] == DT
    np.testing.assert_array_equal(r["positions"], pos)
    assert r["bounds_m"].shape == (3, 2) and r["bounds_m"][0, 1] == 0.4
    assert r["scene"] == "fall" and r["wall_s"] == 1.5 and r["units"]["time"] == "s"
    with h5py.File(tmp_path / "sub" / "r.h5", "r") as f:
        np.testing.assert_allclose(f["velocities"][()], vel)
        np.testing.assert_allclose(f["time"][()], np.arange(len(pos)) * DT)


def test_an_mpm_run_reads_as_a_rollout(tmp_path):
    pos = falling()
    sim_file(tmp_path / "run.h5", pos)
    r = read_rollout(tmp_path / "run.h5")
    assert r["frame_interval_s"] == DT and r["format"] == SIM_FORMAT
    np.testing.assert_array_equal(r["positions"], pos)
    assert r["scene_toml"].startswith("[domain]")  # TOML text, not decoded as JSON


def test_files_written_before_the_layout_had_one_home_still_read(tmp_path):
    """A rollout as gns.export wrote it (plain datasets, default HDF5 version, no SWMR)."""
    pos = falling()
    with h5py.File(tmp_path / "old.h5", "w") as f:
        f.create_dataset("positions", data=pos, chunks=(1, *pos.shape[1:]))
        f.create_dataset("time", data=np.arange(len(pos)) * DT)
        f.attrs.update({"format": "minority-gns-rollout/1", "frame_interval_s": DT,
                        "n_particles": pos.shape[1], "bounds_m": json.dumps(BOUNDS),
                        "units": json.dumps({"positions": "m"})})
    r = read_rollout(tmp_path / "old.h5")
    np.testing.assert_array_equal(r["positions"], pos)
    assert r["bounds_m"].shape == (3, 2) and r["units"] == {"positions": "m"}


def test_a_partial_frame_is_not_read(tmp_path):
    """A writer killed between a frame's positions and its time: len(time) frames count."""
    pos = falling()
    w = sim_file(tmp_path / "run.h5", pos[:4])
    with h5py.File(tmp_path / "run.h5", "a") as f:  # positions of a 5th frame, no time
        f["positions"].resize(5, axis=0)
        f["positions"][4] = pos[4]
    assert w.frames == 4 and frames_written(tmp_path / "run.h5") == 4
    assert read_rollout(tmp_path / "run.h5")["positions"].shape[0] == 4
    assert read_sim(tmp_path / "run.h5")[0].shape[0] == 4


@pytest.mark.parametrize("make, match", [
    (lambda p: p.write_text("not hdf5"), "cannot read the rollout"),
    (lambda p: h5py.File(p, "w").close(), "not a rollout"),
    (lambda p: write_rollout(p, falling(frames=2), falling(frames=2), DT,
                             attrs={"bounds_m": BOUNDS}), r"frames >= 3"),
    (lambda p: write_rollout(p, falling() * np.nan, falling(), DT,
                             attrs={"bounds_m": BOUNDS}), "finite"),
    (lambda p: write_rollout(p, falling(), falling(), DT, attrs={}), "bounds_m"),
])
def test_hostile_files_are_refused(tmp_path, make, match):
    path = tmp_path / "bad.h5"
    make(path)
    with pytest.raises(TrajectoryError, match=match):
        read_rollout(path)

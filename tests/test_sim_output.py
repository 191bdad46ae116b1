"""HDF5 trajectories: layout, attributes, progress, and a run killed with SIGKILL."""

import io
import json
import os
import signal
import subprocess
import sys

import h5py
import numpy as np
import pytest

from minority.protocol.trajectory import (
    PARTICLE_TYPE_SAND,
    SIM_FORMAT,
    open_trajectory,
    read_rollout,
    read_sim,
)
from minority.sim.runner import run_scene
from minority.sim.scene import builtin_scene_path, load_scene

KILL_AFTER_FRAMES = 3


def test_run_scene_writes_trajectory(tmp_path):
    out = tmp_path / "tiny.h5"
    log = io.StringIO()
    summary = run_scene(builtin_scene_path("tiny"), out, stream=log)
    scene = load_scene(builtin_scene_path("tiny"))
    n = 400
    frames = 11  # 0.2 s every 0.02 s, both ends
    assert (summary.particles, summary.frames) == (n, frames)
    assert summary.sim_time_s == pytest.approx(0.2)
    assert summary.steps > 0 and summary.particle_steps_per_s > 0
    assert summary.out_path == out
    with h5py.File(out, "r") as f:
        for name in ("positions", "velocities", "displacements"):
            assert f[name].shape == (frames, n, 3) and f[name].dtype == np.float32
            assert f[name].chunks is not None and f[name].maxshape[0] is None
        assert np.allclose(f["time"][:], np.arange(frames) * 0.02, atol=1e-12)
        assert f["time"].dtype == np.float64
        assert f["kinetic_energy"].shape == (frames,) and f["momentum"].shape == (frames, 3)
        assert f["kinetic_energy"][0] == 0.0 and f["kinetic_energy"][-1] > 0.0
        assert np.array_equal(f["particle_type"][:], np.full(n, PARTICLE_TYPE_SAND))
        assert np.all(f["material"][:] == 30.0)
        pos = f["positions"][:]
        disp = f["displacements"][:]
        assert np.allclose(disp, pos - pos[0], atol=1e-6)
        assert np.isfinite(pos).all()
        a = f.attrs
        assert a["format"] == SIM_FORMAT and a["n_particles"] == n
        assert json.loads(a["units"])["positions"] == "m"
        assert a["output_interval_s"] == 0.02
        assert a["particle_spacing_m"] == pytest.approx(0.01)
        assert a["cell_size_m"] == 0.02
        assert np.allclose(a["bounds_m"], [[0, 0.4], [0, 0.04], [0, 0.16]])
        assert a["scene_toml"] == scene.toml_text and a["dt_mode"] == "cfl" and a["dt_s"] > 0
        assert json.loads(a["material_table"])["friction_angle_deg"] == 30.0
    text = log.getvalue()
    assert "frame 11/11 written" in text and "particle-steps/s" in text
    # the readers of the layout's one home (protocol.trajectory) read the run
    got, attrs = read_sim(out, stride=5)
    np.testing.assert_array_equal(got, pos[::5])
    assert attrs["friction_angle_deg"] == 30.0 and attrs["scene_name"] == "tiny"
    r = read_rollout(out)
    assert r["frame_interval_s"] == 0.02 and r["positions"].shape == (frames, n, 3)
    assert r["material_table"]["friction_angle_deg"] == 30.0 and r["dt_mode"] == "cfl"


def test_quiet_run_prints_nothing(tmp_path):
    log = io.StringIO()
    run_scene(builtin_scene_path("tiny"), tmp_path / "q.h5", progress=False, stream=log)
    assert log.getvalue() == ""


def test_killed_run_keeps_its_frames(tmp_path):
    scene_text = builtin_scene_path("tiny").read_text()
    scene_text = scene_text.replace("duration_s = 0.2", "duration_s = 1000.0")
    scene_text = scene_text.replace("output_interval_s = 0.02", "output_interval_s = 0.005")
    scene_path = tmp_path / "long.toml"
    scene_path.write_text(scene_text)
    out = tmp_path / "killed.h5"
    code = f"from sim.runner import run_scene; run_scene({str(scene_path)!r}, {str(out)!r})"
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:  # wait on the event (a frame written), not on a clock
            if line.startswith(f"frame {KILL_AFTER_FRAMES + 1}/"):
                break
        else:
            pytest.fail(f"run ended before frame {KILL_AFTER_FRAMES + 1}: rc {proc.wait()}")
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    with open_trajectory(out) as f:
        frames = f["time"].shape[0]
        assert frames >= KILL_AFTER_FRAMES + 1
        assert np.allclose(f["time"][:frames], np.arange(frames) * 0.005, atol=1e-12)
        pos = f["positions"][:frames]
        assert np.isfinite(pos).all()
        assert np.abs(pos[-1] - pos[0]).max() > 0.0  # real, moving frames
        assert f.attrs["n_particles"] == 400

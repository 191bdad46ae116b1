"""Teacher-forced acceleration balance (gns.diagnose, minority oracle diagnose)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from minority.gns.dataset import Trajectory
from minority.gns.diagnose import balance, depth_below_surface, regions
from minority.gns.model import GNS, ModelConfig

S = 0.016  # particle spacing, m


def _column(nx=4, ny=3, nz=5, x0=0.1):
    """[nx * ny * nz, 3] lattice points (m), (i + 1/2) S from the corner (x0, 0, 0)."""
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1)
    return (g.reshape(-1, 3) + 0.5) * S + [x0, 0.0, 0.0]


def _stats():
    return {"vel_mean": [0.0] * 3, "vel_std": [1e-3] * 3, "acc_mean": [2e-5, 0.0, -1e-5],
            "acc_std": [1e-4] * 3, "friction_mean_deg": 30.0, "friction_std_deg": 5.0,
            "connectivity_radius_m": 0.029, "frame_interval_s": 0.005,
            "bounds_m": [[0, 1], [0, 0.048], [0, 0.4]], "particle_spacing_m": S,
            "input_velocities": 5}


def _accelerating_run(a: float, frames: int = 30) -> np.ndarray:
    """[frames, n, 3] m: the lattice column, every particle accelerating by a (m/frame^2) in x."""
    k = np.arange(frames)[:, None, None]
    return (_column()[None] + 0.5 * a * k ** 2 * np.array([1.0, 0.0, 0.0])).astype(np.float32)


def _mean_model():
    """A model whose prediction is exactly the statistics' mean acceleration."""
    model = GNS(ModelConfig(latent=8, message_passing=1), _stats()).eval()
    last = model.decoder[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    return model


def test_depth_below_surface_of_a_lattice_column():
    pos = _column()
    depth = depth_below_surface(pos, 0.029)
    layer = np.rint(pos[:, 2] / S - 0.5)
    # bins of 0.029 m hold one or two lattice columns of equal height: depth is top minus z
    np.testing.assert_allclose(depth, (4 - layer) * S, atol=1e-12)
    # a lower column beside the tall one has its own surface
    low = _column(nx=2, nz=2, x0=0.5)
    both = depth_below_surface(np.concatenate([pos, low]), 0.029)
    np.testing.assert_allclose(both[len(pos):], (1 - np.rint(low[:, 2] / S - 0.5)) * S)


def test_regions_split_the_column():
    pos = _column(nx=10, ny=12, nz=3)  # 0.192 m wide
    bounds = np.array([[0, 1], [0, 0.192], [0, 0.4]])
    masks = regions(pos, bounds, 0.029)
    assert masks["all"].all()
    assert not (masks["front"] & masks["behind front"]).any()
    assert masks["front"].sum() == 0.2 * len(pos)
    walls = [m for k, m in masks.items() if k.startswith("side wall")]
    depths = [m for k, m in masks.items() if k.startswith("depth")]
    for group in (walls, depths):  # each a partition of the particles
        np.testing.assert_array_equal(np.sum(group, axis=0), np.ones(len(pos)))
    near = masks["side wall 0-0.03 m"]
    y = pos[near, 1]
    assert np.all((y < 0.03) | (y > 0.192 - 0.03)) and near.sum() == 2 * 2 * 10 * 3


def test_balance_compares_predicted_with_run_accelerations():
    """Every particle accelerates by a per frame in x; the model predicts the mean
    acceleration of its statistics, so the ratio is that over a, in every region."""
    a = 4e-5  # m/frame^2
    x0 = _column()
    traj = Trajectory("const", _accelerating_run(a), 30.0,
                      np.array(_stats()["bounds_m"], np.float64))
    rows = balance(_mean_model(), traj, [(5, 10), (10, 28)])
    assert {r["frames"][0] for r in rows} == {5, 10}
    empty = [r for r in rows if r["particle_frames"] == 0]  # e.g. no particle 0.145 m deep
    assert empty and all(r["ratio"] is None and r["pred_m"] == 0 for r in empty)
    for r in (r for r in rows if r["particle_frames"]):
        n = r["particle_frames"] / (r["frames"][1] - r["frames"][0])
        assert r["true_m"] == pytest.approx(a * n, rel=1e-2)  # float32 positions
        assert r["pred_m"] == pytest.approx(2e-5 * n, rel=1e-5)
        assert r["ratio"] == pytest.approx(0.5, rel=1e-2)
    whole = [r for r in rows if r["region"] == "all"]
    assert [r["particle_frames"] for r in whole] == [5 * len(x0), 18 * len(x0)]
    with pytest.raises(ValueError, match="band 2:10"):
        balance(_mean_model(), traj, [(2, 10)])
    with pytest.raises(ValueError, match="band 20:30"):
        balance(_mean_model(), traj, [(20, 30)])  # frame 29 predicts frame 30


def test_cli_diagnose(tmp_path):
    from minority.gns.train import CHECKPOINT_FORMAT

    torch.save({"format": CHECKPOINT_FORMAT, "model_config": {"latent": 8, "mlp_layers": 2,
                "message_passing": 1, "input_velocities": 5}, "stats": _stats(),
                "state_dict": _mean_model().state_dict(), "step": 0}, tmp_path / "m.pt")
    import h5py

    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "metadata.json").write_text(json.dumps({"format": "minority-gns-dataset/1"}))
    with h5py.File(ds / "test.h5", "w") as f:
        g = f.create_group("const")
        g["positions"] = _accelerating_run(4e-5)
        g.attrs["friction_angle_deg"] = 30.0
        g.attrs["bounds_m"] = np.array(_stats()["bounds_m"], np.float64)
    cmd = [sys.executable, "-m", "minority", "oracle", "diagnose", str(tmp_path / "m.pt"),
           str(ds), "--bands", "6:12", "--threads", "1"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    rows = [json.loads(line) for line in p.stdout.splitlines()]
    assert rows[0]["region"] == "all" and rows[0]["ratio"] == pytest.approx(0.5, rel=1e-2)
    assert "ratio 0.50" in p.stderr
    p = subprocess.run(cmd[:-4] + ["--scene", "nope"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "no scene ['nope']" in p.stderr
    p = subprocess.run(cmd[:-4] + ["--bands", "6-12"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "F0:F1" in p.stderr

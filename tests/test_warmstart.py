"""The oracle's warm start: the first frames from the MPM at the model's spacing."""

import numpy as np
import pytest

from minority.demo import CHECKPOINT, DemoOptions, demo_column
from minority.gns.predict import predict
from minority.gns.rollout import initial_state
from minority.gns.train import load_checkpoint
from minority.warmstart import mpm_history


def test_mpm_history_starts_on_the_gns_lattice_and_falls(tmp_path):
    scene = tmp_path / "column.toml"
    scene.write_text(demo_column(DemoOptions(cell_size_m=0.032, duration_s=0.1)))
    model, ckpt = load_checkpoint(CHECKPOINT, "cpu")
    spacing, dt = ckpt["stats"]["particle_spacing_m"], ckpt["stats"]["frame_interval_s"]
    c = model.config.input_velocities
    h = mpm_history(scene, spacing, dt, c)
    rest = initial_state(scene, spacing, dt, c).positions[0]
    assert h.shape == (c + 1, len(rest), 3)
    order = lambda x: x[np.lexsort(x.T)]  # noqa: E731
    np.testing.assert_allclose(order(h[0]), order(rest), atol=1e-9)  # the same particles
    drop = h[0, :, 2].mean() - h[-1, :, 2].mean()
    assert 0 < drop < 0.5 * 9.81 * (c * dt) ** 2 * 1.01  # falling, at most freely
    p = predict(CHECKPOINT, scene, 0.05, history=h)
    assert p.positions.shape[0] == 11  # 0.05 s at 5 ms, the first c + 1 from the MPM
    np.testing.assert_allclose(p.positions[: c + 1], h, atol=1e-6)


def test_coarse_grained_history_runs_finer_and_starts_on_the_gns_lattice(tmp_path):
    scene = tmp_path / "column.toml"
    scene.write_text(demo_column(DemoOptions(cell_size_m=0.032, duration_s=0.1)))
    spacing, dt, c = 0.016, 0.005, 2
    rest = initial_state(scene, spacing, dt, c).positions[0]
    fine = mpm_history(scene, spacing, dt, c, coarse_grain=2)  # MPM at 0.008 m, cell 0.016
    coarse = mpm_history(scene, spacing, dt, c)
    assert fine.shape == coarse.shape == (c + 1, len(rest), 3)
    order = lambda x: x[np.lexsort(x.T)]  # noqa: E731
    np.testing.assert_allclose(order(fine[0]), order(rest), atol=1e-9)
    assert not np.allclose(fine[-1], coarse[-1])  # another MPM resolution, another motion
    assert fine[0, :, 2].mean() > fine[-1, :, 2].mean()
    # sampled members of the same MPM run: on the lattice at rest, near the means later
    sampled = mpm_history(scene, spacing, dt, c, coarse_grain=2, method="sample")
    np.testing.assert_allclose(order(sampled[0]), order(rest), atol=1e-9)
    assert 0 < np.abs(sampled[-1] - fine[-1]).max() < spacing / 2


def test_mpm_history_refuses_a_domain_it_cannot_seed(tmp_path):
    scene = tmp_path / "odd.toml"
    text = demo_column(DemoOptions(cell_size_m=0.032))
    line = next(t for t in text.splitlines() if t.startswith("size_m"))
    scene.write_text(text.replace(line, "size_m = [0.81, 0.16, 0.416]"))
    with pytest.raises(ValueError, match="cannot seed the MPM at the model's spacing"):
        mpm_history(scene, 0.016, 0.005, 5)


def test_predict_scene_falls_back_to_rest_when_the_mpm_cannot_seed(tmp_path, capsys):
    from minority.warmstart import predict_scene

    scene = tmp_path / "odd.toml"
    text = demo_column(DemoOptions(cell_size_m=0.032))
    line = next(t for t in text.splitlines() if t.startswith("size_m"))
    scene.write_text(text.replace(line, "size_m = [0.81, 0.16, 0.416]"))
    p = predict_scene(CHECKPOINT, scene, 0.02)
    assert "starting from rest instead" in capsys.readouterr().err
    assert p.positions.shape[0] == 5  # t = 0 plus 4 frames of 5 ms, frame 0 at rest
    rest = initial_state(scene, p.spacing_m, p.frame_interval_s, 5).positions[0]
    np.testing.assert_allclose(p.positions[0], rest, atol=1e-6)

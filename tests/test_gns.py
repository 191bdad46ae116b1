"""GNS: sweep planning, dataset packing, model, training, rollout, export."""

import json
import math
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from minority.gns.dataset import build, load_metadata, load_split
from minority.gns.export import write_vtk_series
from minority.gns.model import GNS, ModelConfig, deepen
from minority.gns.rollout import RolloutError, initial_state, rollout
from minority.gns.sweep import ScenePlan, SweepError, load_config, plan
from minority.gns.train import TrainConfig, combined_stats, load_checkpoint, ship, train

SWEEP = Path(__file__).resolve().parent.parent / "gns" / "configs" / "column_sweep.toml"


def test_sweep_plan_holds_out_bands_and_is_deterministic():
    cfg = load_config(SWEEP)
    a, b = plan(cfg), plan(cfg)
    assert a == b
    held_a = cfg.splits["held_out_aspect_ratio"]
    held_phi = cfg.splits["held_out_friction_angle_deg"]

    def held(p):
        return (any(lo <= p.aspect_ratio <= hi for lo, hi in held_a)
                or any(lo <= p.friction_angle_deg <= hi for lo, hi in held_phi))

    for p in a:
        if p.split in ("train", "valid"):
            assert not held(p), p
        elif not p.name.startswith(("showcase", "wide")):
            assert held(p), p
        lo, hi = cfg.geometry["particles"]
        assert p.name.startswith("wide") or lo <= p.particles <= hi
    assert sum(p.split == "train" for p in a) == cfg.splits["train"]
    assert any(any(lo <= p.aspect_ratio <= hi for lo, hi in held_a)
               for p in a if p.split == "test")


def test_sweep_extra_scenes_keep_the_planned_ones():
    """extra_train / extra_valid enlarge a sweep without changing a scene it had."""
    cfg = load_config(SWEEP)
    base = {p.name: p for p in plan(cfg)}
    cfg.splits = {**cfg.splits, "extra_train": 5, "extra_valid": 2}
    grown = plan(cfg)
    assert {p.name: p for p in grown if p.name in base} == base
    added = [p for p in grown if p.name not in base]
    assert sorted(p.split for p in added) == ["train"] * 5 + ["valid"] * 2
    n_train = cfg.splits["train"]
    assert {p.name for p in added if p.split == "train"} == {
        f"train_{i:03d}" for i in range(n_train, n_train + 5)}
    assert len({(p.length_m, p.width_m, p.height_m, p.friction_angle_deg) for p in grown}) \
        == len(grown)


def test_sweep_extends_and_extra_tables_add_scenes_in_their_ranges(tmp_path):
    """A config that extends another keeps the base's scenes; [[extra]] tables draw after
    them from their own geometry ranges, within the held-out rules; bad tables are errors."""
    cfg_long = SWEEP.with_name("column_sweep_cg2_long.toml")
    base = load_config(SWEEP.with_name("column_sweep_cg2.toml"))
    base.splits = {**base.splits, "extra_train": 48, "extra_valid": 4}
    before = {p.name: p for p in plan(base)}
    grown = plan(load_config(cfg_long))
    assert {p.name: p for p in grown if p.name in before} == before
    added = [p for p in grown if p.name not in before]
    assert sorted(p.split for p in added) == ["train"] * 12 + ["valid"] * 2
    assert {p.name for p in added if p.split == "valid"} == {"valid_008", "valid_009"}
    held_a = base.splits["held_out_aspect_ratio"][0]
    held_phi = base.splits["held_out_friction_angle_deg"][0]
    for p in added:
        assert 0.2 - 1e-9 <= p.length_m <= 0.32 + 1e-9 and p.width_m in (0.096, 0.128), p
        assert 800 <= p.particles <= 3000, p
        assert not held_a[0] <= p.aspect_ratio <= held_a[1], p
        assert not held_phi[0] <= p.friction_angle_deg <= held_phi[1], p
    assert max(p.length_m for p in before.values() if p.split != "test") <= 0.2 + 1e-9

    bad = tmp_path / "bad.toml"
    for table, word in (('split = "test"\ncount = 2', "split"),
                        ('split = "train"\ncount = 0', "count"),
                        ('split = "train"\ncount = "2"', "count"),
                        ('split = "train"\ncount = 1\nlenght_m = [0.2, 0.3]', "lenght_m"),
                        ('split = "train"\ncount = 1\ncell_size_m = 0.016', "cell_size_m")):
        bad.write_text(f'extends = "{cfg_long}"\n[[extra]]\n{table}\n')
        with pytest.raises(SweepError, match=word):
            load_config(bad)
    bad.write_text(f'extends = "{bad.name}"\n')
    with pytest.raises(SweepError, match="loops back"):
        load_config(bad)


def test_cli_dataset_extra_scenes_override_the_config(monkeypatch, tmp_path, capsys):
    from minority.cli import main
    from minority.gns import sweep as gns_sweep

    seen = {}

    def fake_sweep(cfg, out, **kw):
        seen["plans"] = plan(cfg)
        raise gns_sweep.SweepError("stop before running")

    from minority import sweep

    monkeypatch.setattr(sweep, "run_sweep", fake_sweep)
    rc = main(["oracle", "dataset", "--config", str(SWEEP), "--runs", str(tmp_path / "r"),
               "--out", str(tmp_path / "d"), "--extra-train", "3", "--extra-valid", "1"])
    assert rc == 1 and "stop before running" in capsys.readouterr().err
    cfg = load_config(SWEEP)
    assert len(seen["plans"]) == len(plan(cfg)) + 4
    assert sum(p.split == "valid" for p in seen["plans"]) == cfg.splits["valid"] + 1


def _fake_run(path: Path, rng, n=60, frames=30, phi=30.0, size=(0.4, 0.1, 0.2)):
    """A trajectory in `minority sim`'s HDF5 layout: particles falling and drifting."""
    x0 = rng.uniform(0.05, 0.09, (n, 3))
    t = np.arange(frames) * 0.0025
    pos = x0[None] + np.stack([0.2 * t, 0 * t, -0.5 * 9.81 * t * t], 1)[:, None, :] * 0.1
    with h5py.File(path, "w") as f:
        f["positions"] = pos.astype(np.float32)
        f["time"] = t
        f["material"] = np.full(n, phi, np.float32)
        f.attrs["output_interval_s"] = 0.0025
        f.attrs["bounds_m"] = np.array([[0.0, s] for s in size])
        f.attrs["particle_spacing_m"] = 0.016
        f.attrs["scene_name"] = path.stem
    return pos


def _plan(name, split, phi=30.0):
    return ScenePlan(name, split, 0.1, 0.1, 0.1, phi, 0.4, 60)


@pytest.fixture
def dataset(tmp_path):
    rng = np.random.default_rng(0)
    runs, raw = [], []
    for i, (split, phi) in enumerate([("train", 28.0), ("train", 34.0), ("valid", 30.0),
                                      ("test", 35.0)]):
        p = tmp_path / f"r{i}.h5"
        raw.append((split, _fake_run(p, rng, phi=phi)))
        runs.append((_plan(f"{split}_{i}", split, phi), p))
    meta = build(runs, tmp_path / "ds", stride=2, connectivity_radius_m=0.029)
    return tmp_path / "ds", meta, raw


def test_dataset_metadata_and_stats(dataset):
    path, meta, raw = dataset
    assert load_metadata(path) == json.loads(json.dumps(meta))
    assert meta["frame_interval_s"] == pytest.approx(0.005)
    assert meta["connectivity_radius_m"] == 0.029 and meta["dim"] == 3
    train_pos = [p[::2].astype(np.float32).astype(np.float64) for s, p in raw if s == "train"]
    v = np.concatenate([np.diff(p, axis=0).reshape(-1, 3) for p in train_pos])
    a = np.concatenate([np.diff(p, 2, axis=0).reshape(-1, 3) for p in train_pos])
    np.testing.assert_allclose(meta["vel_mean"], v.mean(0), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(meta["vel_std"], v.std(0), rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(meta["acc_std"], a.std(0), rtol=1e-3, atol=1e-9)
    assert meta["friction_mean_deg"] == pytest.approx(31.0)
    assert [t.name for t in load_split(path, "test")] == ["test_3"]
    assert {s["split"] for s in meta["scenes"]} == {"train", "valid", "test"}


def _stats():
    return {"vel_mean": [0.0] * 3, "vel_std": [1e-3] * 3, "acc_mean": [0.0] * 3,
            "acc_std": [1e-4] * 3, "friction_mean_deg": 30.0, "friction_std_deg": 5.0,
            "connectivity_radius_m": 0.03, "frame_interval_s": 0.005,
            "bounds_m": [[0, 1], [0, 1], [0, 1]], "particle_spacing_m": 0.016,
            "input_velocities": 5}


def _inputs(n=50, seed=0):
    from minority.gns.graph import radius_graph
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.2, 0.3, (n, 3))
    pos = x[:, None, :] + np.cumsum(rng.normal(0, 1e-3, (n, 6, 3)), axis=1)
    s, r = radius_graph(pos[:, -1], 0.03)
    return (torch.tensor(pos, dtype=torch.float32), torch.full((n,), 31.0),
            torch.tensor([[0.0, 1], [0, 1], [0, 1]]), torch.tensor(s), torch.tensor(r))


def test_model_is_permutation_equivariant():
    torch.manual_seed(0)
    model = GNS(ModelConfig(latent=16, message_passing=2), _stats()).eval()
    pos, fr, b, s, r = _inputs()
    perm = torch.randperm(pos.shape[0])
    inv = torch.argsort(perm)
    with torch.no_grad():
        out = model(pos, fr, b, s, r)
        out_p = model(pos[perm], fr[perm], b, inv[s], inv[r])
    torch.testing.assert_close(out_p, out[perm], rtol=1e-4, atol=1e-5)
    assert out.shape == (pos.shape[0], 3)


def test_split_first_layer_equals_concatenated_mlp():
    torch.manual_seed(1)
    model = GNS(ModelConfig(latent=8, message_passing=1), _stats())
    blk = model.processor[0]
    h, e = torch.randn(20, 8), torch.randn(40, 8)
    s, r = torch.randint(0, 20, (40,)), torch.randint(0, 20, (40,))
    f = blk.edge.first
    w = torch.cat([f[0].weight, f[1].weight, f[2].weight], dim=1)
    cat = torch.cat([e, h[s], h[r]], dim=1) @ w.T + f[0].bias
    e_ref = blk.edge.rest(torch.relu(cat))
    agg = torch.zeros(20, 8).index_add_(0, r, e_ref)
    g = blk.node.first
    h_ref = blk.node.rest(torch.relu(torch.cat([h, agg], 1) @ torch.cat(
        [g[0].weight, g[1].weight], 1).T + g[0].bias))
    h_new, e_new = blk(h, e, s, r)
    torch.testing.assert_close(e_new, e + e_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(h_new, h + h_ref, rtol=1e-5, atol=1e-5)


def test_train_checkpoint_resume_and_rollout(dataset, tmp_path):
    path, meta, _ = dataset
    out = tmp_path / "m.pt"
    tc = TrainConfig(steps=6, batch=2, val_every=3, val_frames=5, ckpt_every=3)
    mc = ModelConfig(latent=16, message_passing=2)
    train(path, out, mc, tc, device="cpu")
    model, ckpt = load_checkpoint(out)  # weights_only=True inside
    assert ckpt["step"] == 6 and ckpt["model_config"] == mc.to_dict()
    assert ckpt["stats"]["acc_std"][0] == pytest.approx(
        math.hypot(meta["acc_std"][0], tc.noise_std))
    assert any("val_error_m" in h for h in ckpt["history"])
    assert not any("val_runout_error_max" in h for h in ckpt["history"])  # partial rollouts
    complete = [h for h in ckpt["history"] if h.get("val_complete")]
    assert (tmp_path / "m.best.pt").exists() == bool(complete)
    train(path, out, mc, replace(tc, steps=9, val_frames=10_000, keep_validated=True),
          resume=out, device="cpu")
    assert (tmp_path / "m_step9.pt").exists() and not (tmp_path / "m_step6.pt").exists()
    full = [h for h in load_checkpoint(out)[1]["history"] if h.get("step") == 9
            and "val_error_m" in h]
    from minority.gns.rollout import rollout_error  # full-length rollouts: the worst scene's errors
    vals = [rollout_error(load_checkpoint(out)[0], t, 10_000) for t in load_split(path, "valid")]
    for key in ("runout", "displacement_range"):
        assert full[0][f"val_{key}_error_max"] == pytest.approx(max(v[key] for v in vals))
    assert full[0]["val_runout_signed"] == pytest.approx([v["runout_signed"] for v in vals])
    assert full[0]["val_height_signed"] == pytest.approx([v["height_signed"] for v in vals])
    from minority.gns.metrics import HEIGHT_QUANTILE
    for v, t in zip(vals, load_split(path, "valid"), strict=True):  # > 0: too tall
        pred, _ = rollout(load_checkpoint(out)[0], t.positions[:6].astype(np.float64),
                          t.friction_angle_deg, t.bounds_m, t.positions.shape[0] - 6)
        got, ref = (np.quantile(p[-1, :, 2].astype(np.float64), HEIGHT_QUANTILE)
                    for p in (pred, t.positions))
        assert v["height_signed"] == pytest.approx((got - ref) / ref)
    assert [abs(v["runout_signed"]) for v in vals] == pytest.approx([v["runout"] for v in vals])
    model2, ckpt2 = load_checkpoint(out)
    assert ckpt2["step"] == 9
    traj = load_split(path, "valid")[0]
    pred, timing = rollout(model2, traj.positions[:6].astype(np.float64),
                           traj.friction_angle_deg, traj.bounds_m, 4)
    assert pred.shape == (10, traj.positions.shape[1], 3) and np.isfinite(pred).all()
    np.testing.assert_array_equal(pred[:6], traj.positions[:6])
    assert timing["model_s"] > 0


def test_train_ema_saves_the_average_and_resumes_it(dataset, tmp_path):
    """state_dict is the moving average, train_state_dict the optimizer's weights; a resumed
    run continues the average (one step: ema = d * ema + (1 - d) * weights)."""
    path, _, _ = dataset
    out, d = tmp_path / "e.pt", 0.75
    tc = TrainConfig(steps=1, batch=1, val_every=10, ckpt_every=1, ema_decay=d)
    train(path, out, ModelConfig(latent=8, message_passing=1), tc, device="cpu")
    first = torch.load(out, weights_only=True)
    for k, v in first["state_dict"].items():  # the first update copies the weights
        torch.testing.assert_close(v, first["train_state_dict"][k])
    train(path, out, None, replace(tc, steps=2), resume=out, device="cpu")
    second = torch.load(out, weights_only=True)
    moved = 0
    for k, v in second["state_dict"].items():
        w = second["train_state_dict"][k]
        if v.is_floating_point() and not torch.equal(w, first["train_state_dict"][k]):
            moved += 1
            torch.testing.assert_close(v, d * first["state_dict"][k] + (1 - d) * w)
    assert moved > 0
    model, _ = load_checkpoint(out)
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, second["state_dict"][k])
    shipped = torch.load(ship(out, tmp_path / "s.pt"), weights_only=True)
    assert "train_state_dict" not in shipped and "optimizer" not in shipped


def test_pushforward_unroll_is_the_rollout_and_draws_steps():
    from minority.gns.pushforward import draw_steps, unroll
    torch.manual_seed(0)
    model = GNS(ModelConfig(latent=8, message_passing=1), _stats()).eval()
    pos = _inputs()[0].numpy().astype(np.float64)  # [n, C+1, 3]
    bounds = np.array([[0.0, 1], [0, 1], [0, 0.28]])  # some particles start above the top
    pred, _ = rollout(model, pos.transpose(1, 0, 2), 31.0, bounds, 3)
    got = unroll(model, pos, 31.0, bounds, 3)
    np.testing.assert_allclose(got.transpose(1, 0, 2), pred[-6:], atol=1e-6)
    assert got[:, -1, 2].max() <= np.float32(0.28)  # clamped to the domain as the rollout clamps
    rng = np.random.default_rng(0)
    assert {draw_steps(rng, 3, 0.0) for _ in range(50)} == {0}
    assert {draw_steps(rng, 0, 1.0) for _ in range(50)} == {0}
    assert {draw_steps(rng, 3, 1.0) for _ in range(200)} == {1, 2, 3}
    assert 0.3 < np.mean([draw_steps(rng, 3, 0.5) > 0 for _ in range(1000)]) < 0.7


def test_pushforward_window_targets_the_true_velocity_from_the_advanced_inputs(dataset):
    from minority.gns.train import Sampler
    path, _, _ = dataset
    trajs = load_split(path, "train")
    seen = []

    def advance(inputs, friction, bounds, steps):  # stands in for the model: shifts by 1 mm
        seen.append((inputs.copy(), steps))
        return inputs + 1e-3

    sampler = Sampler(trajs, 5, 0.0, np.random.default_rng(1))
    for _ in range(20):
        inputs, target, fr, _b, s, r = sampler.window(0.029, 2, advance)
        start, steps = seen[-1]
        assert steps == 2 and inputs.shape == start.shape == (trajs[0].positions.shape[1], 6, 3)
        np.testing.assert_allclose(inputs, start + 1e-3)
        t = next(t for t in trajs if t.friction_angle_deg == fr[0])
        k = next(k for k in range(t.positions.shape[0] - 7)  # the window's first frame
                 if np.allclose(t.positions[k:k + 6].transpose(1, 0, 2), start))
        last = k + 5 + 2  # the last input frame: 2 frames on; the target velocity is its
        np.testing.assert_allclose(target - inputs[:, -1], t.positions[last + 1] - t.positions[last],
                                   atol=1e-9)
        assert len(s) == len(r) and (len(s) == 0 or s.max() < inputs.shape[0])


def test_train_with_pushforward_unrolls_the_model(dataset, tmp_path, monkeypatch):
    from minority.gns import train as gns_train
    path, _, _ = dataset
    calls = []
    real = gns_train.unroll

    def counting(model, inputs, friction, bounds, steps, device):
        calls.append(steps)
        return real(model, inputs, friction, bounds, steps, device)

    monkeypatch.setattr(gns_train, "unroll", counting)
    tc = TrainConfig(steps=4, batch=2, val_every=10, ckpt_every=4, pushforward_steps=3,
                     pushforward_prob=1.0)
    out = train(path, tmp_path / "p.pt", ModelConfig(latent=8, message_passing=1), tc,
                device="cpu")
    assert len(calls) == 8 and set(calls) <= {1, 2, 3}
    assert load_checkpoint(out)[1]["train_config"]["pushforward_steps"] == 3
    calls.clear()
    train(path, tmp_path / "q.pt", ModelConfig(latent=8, message_passing=1),
          replace(tc, pushforward_prob=0.0), device="cpu")
    assert calls == []
    with pytest.raises(ValueError, match="pushforward"):
        train(path, tmp_path / "b.pt", ModelConfig(latent=8, message_passing=1),
              replace(tc, pushforward_prob=1.5), device="cpu")


def test_rollout_divergence_names_the_frame():
    torch.manual_seed(0)
    stats = _stats()
    model = GNS(ModelConfig(latent=8, message_passing=1), stats).eval()
    with torch.no_grad():
        model.decoder[-1].bias.fill_(0.0)
        model.decoder[-1].weight.fill_(0.0)
        model.decoder[-1].bias[2] = -2000.0  # -0.2 m/frame^2: falls through the floor
    pos = _inputs()[0].numpy().transpose(1, 0, 2).astype(np.float64)
    bounds = np.array([[0.0, 1], [0, 1], [0, 1]])
    with pytest.raises(RolloutError, match=r"diverged at frame \d+: particle \d+ left the domain"):
        rollout(model, pos, 30.0, bounds, 50)
    with torch.no_grad():
        model.decoder[-1].bias[2] = float("nan")
    with pytest.raises(RolloutError, match="diverged at frame 6: non-finite"):
        rollout(model, pos, 30.0, bounds, 5)


def test_initial_state_matches_the_mpm_seeding():
    from minority.sim.scene import builtin_scene_path, load_scene
    from minority.sim.state import seed_particles

    path = builtin_scene_path("tiny")
    scene = load_scene(path)
    init = initial_state(path, scene.particle_spacing_m, 0.005, 5)
    x = seed_particles(scene).x
    assert init.positions.shape == (6, len(x), 3)
    np.testing.assert_allclose(init.positions[-1], x)
    assert init.friction_deg == scene.material.friction_angle_deg
    np.testing.assert_allclose(init.bounds_m[:, 1], scene.size_m)


def test_vtk_series_opens_with_arrays(tmp_path):
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    rng = np.random.default_rng(0)
    pos = np.cumsum(rng.normal(0, 1e-3, (4, 30, 3)), axis=0).astype(np.float32)
    pvd = write_vtk_series(tmp_path, pos, 0.005)
    text = pvd.read_text()
    assert text.count("<DataSet") == 4 and 'timestep="0.015"' in text
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(tmp_path / "rollout_000003.vtp"))
    reader.Update()
    poly = reader.GetOutput()
    assert poly.GetNumberOfPoints() == 30 and poly.GetNumberOfVerts() == 30
    from vtkmodules.util.numpy_support import vtk_to_numpy
    disp = vtk_to_numpy(poly.GetPointData().GetArray("displacement"))
    np.testing.assert_allclose(disp, pos[3] - pos[0], atol=1e-7)
    vel = vtk_to_numpy(poly.GetPointData().GetArray("velocity"))
    np.testing.assert_allclose(vel, (pos[3] - pos[2]) / 0.005, rtol=1e-5, atol=1e-5)
    speed = vtk_to_numpy(poly.GetPointData().GetArray("velocity_magnitude"))
    np.testing.assert_allclose(speed, np.linalg.norm(vel, axis=1), rtol=1e-6)
    assert poly.GetFieldData().GetArray("TimeValue").GetValue(0) == 0.015


def test_inference_path_equals_autograd_path():
    torch.manual_seed(2)
    import minority.gns.model as gm
    model = GNS(ModelConfig(latent=16, message_passing=3), _stats()).eval()
    pos, fr, b, s, r = _inputs(n=300)
    ref = model(pos, fr, b, s, r).detach()  # autograd path
    old = gm.CHUNK_EDGES
    try:
        gm.CHUNK_EDGES = 97  # several chunks, the last one partial
        with torch.no_grad():
            fast = model(pos, fr, b, s, r)
    finally:
        gm.CHUNK_EDGES = old
    assert len(s) > 3 * 97
    torch.testing.assert_close(fast, ref, rtol=1e-4, atol=1e-4)


def test_deposit_measures():
    from minority.gns.metrics import deposit, relative_errors
    x0 = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(10), indexing="ij"),
                  -1).reshape(-1, 3) * 0.01
    x1 = x0 * np.array([2.0, 1.0, 0.5])
    d = deposit(np.stack([x0, x1]))
    assert d.runout_m == pytest.approx(np.quantile(x1[:, 0], 0.99))
    assert d.height_m == pytest.approx(np.quantile(x1[:, 2], 0.99))
    assert d.displacement_min_m == 0.0
    assert d.displacement_max_m == pytest.approx(np.hypot(0.09, 0.045))
    e = relative_errors(deposit(np.stack([x0, x1 * 1.1])), d)
    assert e["runout"] == pytest.approx(0.1) and e["height"] == pytest.approx(0.1)


def test_cli_train_rollout_evaluate(dataset, tmp_path):
    import subprocess
    import sys
    path, _, _ = dataset
    ck = tmp_path / "c.pt"
    run = [sys.executable, "-m", "minority", "oracle"]
    p = subprocess.run(run + ["train", str(path), "--out", str(ck), "--latent", "8",
                              "--message-passing", "1", "--steps", "3", "--val-every", "3",
                              "--val-frames", "3"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "validation rollout mean position error" in p.stderr
    p = subprocess.run(run + ["evaluate", str(ck), str(path), "--out", str(tmp_path / "e.json")],
                       capture_output=True, text=True, timeout=120)
    doc = json.loads((tmp_path / "e.json").read_text())
    assert [r["scene"] for r in doc["scenes"]] == ["test_3"] and doc["step"] == 3
    assert p.returncode == (0 if "error" not in doc["scenes"][0] else 1)
    out = tmp_path / "roll"
    p = subprocess.run(run + ["rollout", str(ck), "tiny", "--out", str(out), "--duration",
                              "0.02", "--vtk-every", "2"], capture_output=True, text=True,
                       timeout=120)
    if p.returncode == 0:
        with h5py.File(out / "rollout.h5", "r") as f:
            from minority.sim.scene import builtin_scene_path
            n = initial_state(builtin_scene_path("tiny"), 0.016, 0.005, 5).positions.shape[1]
            assert f["positions"].shape == (5, n, 3)  # t = 0 plus 4 frames of 0.005 s
            np.testing.assert_allclose(f["time"][:], np.arange(5) * 0.005)
        assert len(list((out / "vtk").glob("*.vtp"))) == 3
        assert (out / "vtk" / "rollout.pvd").exists()
    else:  # an untrained model may leave the domain: then the error names the frame
        assert "rollout diverged at frame" in p.stderr, p.stderr
    p = subprocess.run(run + ["ship", str(ck), "-o", str(tmp_path / "s.pt")], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    shipped = torch.load(tmp_path / "s.pt", weights_only=True)
    assert "optimizer" not in shipped and shipped["step"] == 3
    assert (tmp_path / "s.pt").stat().st_size < ck.stat().st_size
    p = subprocess.run(run + ["rollout", str(tmp_path / "missing.pt"), "tiny"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "missing.pt" in p.stderr


def test_deepen_appends_identity_steps_that_then_learn():
    """A deepened model predicts what the original does on both paths, and its new steps
    get gradients (their zero LayerNorm scale and shift), so training can use them."""
    torch.manual_seed(3)
    model = GNS(ModelConfig(latent=16, message_passing=2), _stats()).eval()
    pos, fr, b, s, r = _inputs(n=120)
    deeper = deepen(model, _stats(), 5).eval()
    assert deeper.config.message_passing == 5 and len(deeper.processor) == 5
    with torch.no_grad():
        torch.testing.assert_close(deeper(pos, fr, b, s, r), model(pos, fr, b, s, r))
    out = deeper(pos, fr, b, s, r)  # autograd path
    torch.testing.assert_close(out.detach(), model(pos, fr, b, s, r).detach())
    out.square().sum().backward()
    new_norm = deeper.processor[4].node.rest[-1]
    assert new_norm.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="has 2 already"):
        deepen(model, _stats(), 2)


def test_train_init_deepen(dataset, tmp_path):
    path, _, _ = dataset
    base, deep = tmp_path / "base.pt", tmp_path / "deep.pt"
    tc = TrainConfig(steps=2, batch=2, val_every=100, val_frames=5, ckpt_every=2)
    train(path, base, ModelConfig(latent=8, message_passing=1), tc, device="cpu")
    train(path, deep, ModelConfig(), tc, init=base, deepen_to=3, device="cpu")
    model, ckpt = load_checkpoint(deep)
    assert ckpt["model_config"]["message_passing"] == 3 and len(model.processor) == 3
    assert ckpt["history"][0]["deepened_from"] == 1
    with pytest.raises(ValueError, match="deepen_to needs init"):
        train(path, deep, ModelConfig(), tc, resume=base, deepen_to=3, device="cpu")


def test_init_fine_tunes_from_weights_with_a_fresh_schedule(dataset, tmp_path):
    path, _, _ = dataset
    base, tuned = tmp_path / "base.pt", tmp_path / "tuned.pt"
    tc = TrainConfig(steps=4, batch=2, val_every=100, val_frames=5, ckpt_every=4)
    train(path, base, ModelConfig(latent=16, message_passing=2), tc, device="cpu")
    _, start = load_checkpoint(base)
    # the model config given here is ignored: the checkpoint's wins
    train(path, tuned, ModelConfig(latent=8, message_passing=1),
          replace(tc, steps=3, noise_std=1e-4), init=base, device="cpu")
    model, ckpt = load_checkpoint(tuned)
    assert ckpt["step"] == 3 and ckpt["model_config"] == start["model_config"]
    assert ckpt["stats"] == {**start["stats"], "coarse_grain": 1, "coarse_grain_method": "mean"}
    assert ckpt["history"][0] == {"init": str(base), "init_step": 4}
    assert ckpt["train_config"]["noise_std"] == 1e-4
    changed = [not torch.equal(ckpt["state_dict"][k], start["state_dict"][k])
               for k in start["state_dict"]]
    assert any(changed)
    with pytest.raises(ValueError, match="resume and init are exclusive"):
        train(path, tuned, ModelConfig(), tc, resume=base, init=base, device="cpu")


def test_train_options_that_cannot_go_together_are_named_as_flags(dataset, tmp_path, capsys):
    """The library names its arguments (resume, init, deepen_to); the command its flags."""
    from minority.cli import main

    path, _, _ = dataset
    base = tmp_path / "base.pt"
    base.write_bytes(b"not read: refused before")
    argv = ["oracle", "train", str(path), "--out", str(tmp_path / "x.pt")]
    assert main([*argv, "--resume", str(base), "--init", str(base)]) == 2
    assert "give --resume or --init, not both" in capsys.readouterr().err
    assert main([*argv, "--resume", str(base), "--deepen", "3"]) == 2
    assert "--deepen needs --init" in capsys.readouterr().err


def test_coarse_grain_averages_the_groups_of_each_coarse_cube():
    from minority.gns.dataset import coarse_grain

    fine = 0.5  # m
    idx = np.stack(np.meshgrid(np.arange(4), np.arange(2), np.arange(3), indexing="ij"), -1)
    x0 = (idx.reshape(-1, 3) + 0.5) * fine  # 4 x 2 x 3 lattice: two whole cubes, one half cube
    rng = np.random.default_rng(0)
    later = x0 + rng.normal(0.0, 0.1, x0.shape)
    got = coarse_grain(np.stack([x0, later]), fine, 2)
    assert got.shape == (2, 4, 3)
    # frame 0: the whole cubes' means sit on the coarse lattice (j + 1/2) * 2 * fine
    np.testing.assert_allclose(got[0, [0, 2]], [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]])
    cube = np.floor(x0 / 1.0).astype(int)
    for k, key in enumerate([(0, 0, 0), (0, 0, 1), (1, 0, 0), (1, 0, 1)]):  # sorted cubes
        members = (cube == key).all(axis=1)
        assert members.sum() == (8 if key[2] == 0 else 4)
        np.testing.assert_allclose(got[1, k], later[members].mean(axis=0))
    assert coarse_grain(got, 1.0, 1) is got


def test_coarse_grain_config_runs_the_mpm_finer():
    from minority.sweep import scene_toml

    cfg = load_config(SWEEP.with_name("column_sweep_cg2.toml"))
    coarse = load_config(SWEEP)
    assert cfg.coarse_grain == 2 and coarse.coarse_grain == 1
    p = plan(cfg)[0]
    assert "cell_size_m = 0.016" in scene_toml(cfg, p)
    assert "cell_size_m = 0.032" in scene_toml(coarse, plan(coarse)[0])
    assert [q.name for q in plan(cfg)][-2:] == ["showcase", "wide_10x"]


def test_evaluate_and_validation_measure_the_same_rollout_error(dataset, tmp_path):
    """Both average over the predicted frames only (the C+1 MPM frames a rollout starts from
    have no error), and agree on the deposit errors."""
    from minority.gns.evaluate import evaluate
    from minority.gns.rollout import rollout_error

    path, _, _ = dataset
    out = tmp_path / "m.pt"
    train(path, out, ModelConfig(latent=16, message_passing=2),
          TrainConfig(steps=3, batch=2, val_every=3, val_frames=5, ckpt_every=3), device="cpu")
    model, _ = load_checkpoint(out)
    (row,) = evaluate(model, path, "valid")
    val = rollout_error(model, load_split(path, "valid")[0], 10_000)
    assert row["mean_position_error_m"] == pytest.approx(val["error_m"], rel=1e-12)
    assert row["relative_error"]["runout"] == pytest.approx(val["runout"], rel=1e-12)
    assert "relative_error_full" not in row  # not coarse-grained: the data are the run


def test_a_coarse_grained_dataset_scores_against_the_run_at_its_resolution(tmp_path):
    """The metadata keep each MPM run's own deposit; evaluate scores the rollout against it
    as well as against the coarse-grained data."""
    from minority.gns.evaluate import evaluate
    from minority.gns.metrics import Deposit, deposit, relative_errors

    rng = np.random.default_rng(5)
    runs, raw = [], {}
    for i, split in enumerate(["train", "train", "valid"]):
        p = tmp_path / f"r{i}.h5"
        raw[f"{split}_{i}"] = _fake_run(p, rng, n=200)
        runs.append((_plan(f"{split}_{i}", split), p))
    meta = build(runs, tmp_path / "ds", stride=2, connectivity_radius_m=0.058, coarse_grain=2)
    for sc in meta["scenes"]:
        run = raw[sc["name"]][::2].astype(np.float32)
        assert sc["mpm_deposit"] == pytest.approx(deposit(run).as_dict(), rel=1e-12)
        assert sc["particles"] < 200  # coarse-grained
    out = tmp_path / "m.pt"
    train(tmp_path / "ds", out, ModelConfig(latent=16, message_passing=2),
          TrainConfig(steps=2, batch=2, val_every=2, val_frames=5, ckpt_every=2), device="cpu")
    model, _ = load_checkpoint(out)
    (row,) = evaluate(model, tmp_path / "ds", "valid")
    full = deposit(raw["valid_2"][::2].astype(np.float32))
    assert row["mpm_full"] == pytest.approx(full.as_dict(), rel=1e-12)
    assert row["relative_error_full"] == pytest.approx(
        relative_errors(Deposit(**row["gns"]), full), rel=1e-12)
    assert row["mpm"] != row["mpm_full"]


def test_one_friction_angle_and_a_still_axis_give_finite_features(tmp_path):
    """Every train scene at 30 deg (friction std 0) and no motion along y (velocity and
    acceleration std 0 there): the statistics stay positive, the model's inputs finite."""
    rng = np.random.default_rng(3)
    runs = []
    for i in range(2):
        p = tmp_path / f"r{i}.h5"
        _fake_run(p, rng, phi=30.0)
        with h5py.File(p, "a") as f:
            pos = f["positions"][()]
            pos[:, :, 1] = pos[:1, :, 1]  # y never changes
            f["positions"][...] = pos
        runs.append((_plan(f"train_{i}", "train"), p))
    meta = build(runs, tmp_path / "ds", stride=2, connectivity_radius_m=0.029)
    assert meta["friction_std_deg"] == 1.0
    assert min(meta["vel_std"] + meta["acc_std"]) > 0.0
    model = GNS(ModelConfig(latent=8, message_passing=1), combined_stats(meta, 0.0))
    traj = load_split(tmp_path / "ds", "train")[0]
    pos = torch.as_tensor(np.transpose(traj.positions[:6], (1, 0, 2)), dtype=torch.float32)
    from minority.gns.graph import radius_graph

    s, r = radius_graph(traj.positions[5].astype(np.float64), 0.029)
    with torch.no_grad():
        nodes, edges = model.features(pos, torch.full((pos.shape[0],), 30.0),
                                      torch.as_tensor(traj.bounds_m, dtype=torch.float32),
                                      torch.as_tensor(s), torch.as_tensor(r))
    assert torch.isfinite(nodes).all() and torch.isfinite(edges).all()

"""Datasets from other simulators and projects: a run of any simulator in the documented HDF5
layout (protocol.trajectory.read_trajectory) with only the required datasets, errors that
name what is missing or malformed, the dataset built from such runs (oracle dataset
--from-runs), a few training steps on runs of a simulator that is not our MPM, and the npz
layout of geoelements/gns both ways (export-npz, dataset --from-npz)."""

import json
import math
import pickle
import zipfile

import h5py
import numpy as np
import pytest

from minority.cli import main
from minority.gns.dataset import load_metadata, load_split
from minority.gns.from_runs import build_from_runs, collect, estimate_spacing
from minority.gns.npz import NpzError, export_npz, import_npz, load_npz
from minority.protocol.trajectory import TrajectoryError, read_trajectory

DT = 0.005  # s between frames
S = 0.02  # particle spacing, m
BOUNDS = [[0.0, 1.0], [0.0, 0.1], [0.0, 0.5]]  # m


def slide(path, phi_deg, *, frames=16, slope_deg=35.0, kinematic=True, material=True,
          spacing_attr=False, name=None):
    """Another simulator's run, written with h5py alone: a block of grains sliding down a
    slope under gravity, with basal friction phi_deg (a = g (sin a - tan phi cos a), none
    once friction holds), stopped at the floor; the slope's surface as kinematic particles
    (type 3) that stay put. Only the required datasets unless asked. Returns the moving
    particles' positions [frames, n, 3] (m)."""
    g, a = 9.81, math.radians(slope_deg)
    acc = max(g * (math.sin(a) - math.tan(math.radians(phi_deg)) * math.cos(a)), 0.0)
    ix, iy, iz = np.meshgrid(np.arange(4), np.arange(3), np.arange(3), indexing="ij")
    block = (np.stack([ix, iy, iz], -1).reshape(-1, 3) + 0.5) * S  # [36, 3] m, in the slope's frame
    down = np.array([math.cos(a), 0.0, -math.sin(a)])  # down the slope
    normal = np.array([math.sin(a), 0.0, math.cos(a)])
    origin = np.array([0.05, 0.0, 0.35])
    x0 = origin + block[:, :1] * down + block[:, 1:2] * [0, 1, 0] + block[:, 2:] * normal
    t = np.arange(frames) * DT
    pos = x0[None] + (0.5 * acc * t * t)[:, None, None] * down
    pos[..., 2] = np.maximum(pos[..., 2], S / 2)
    surface = origin + (np.arange(8)[:, None] * S) * down  # [8, 3] kinematic, m
    types = np.full(len(x0), 6)
    if kinematic:
        pos_all = np.concatenate([pos, np.broadcast_to(surface, (frames, 8, 3))], axis=1)
        types = np.concatenate([types, np.full(8, 3)])
    else:
        pos_all = pos
    with h5py.File(path, "w") as f:
        f["positions"] = pos_all.astype(np.float32)
        f.attrs["frame_interval_s"] = DT
        f.attrs["bounds_m"] = np.array(BOUNDS)
        if kinematic:
            f["particle_type"] = types.astype(np.int32)
        if material:
            f["material"] = np.full(len(types), phi_deg, np.float32)
        if spacing_attr:
            f.attrs["particle_spacing_m"] = S
        if name:
            f.attrs["name"] = name
    return pos.astype(np.float32)


def test_a_run_with_only_the_required_datasets_reads(tmp_path):
    pos = slide(tmp_path / "run.h5", 20.0, kinematic=False, material=False)
    run = read_trajectory(tmp_path / "run.h5")
    np.testing.assert_array_equal(run.positions, pos)
    assert run.frame_interval_s == DT and run.bounds_m.tolist() == BOUNDS
    assert run.name == "run" and (run.particle_type == 6).all()
    assert run.material is None and run.particle_spacing_m is None
    half = read_trajectory(tmp_path / "run.h5", stride=2)
    assert half.frame_interval_s == 2 * DT and len(half.positions) == 8


def test_the_frame_interval_comes_from_uniform_times(tmp_path):
    slide(tmp_path / "run.h5", 20.0)
    with h5py.File(tmp_path / "run.h5", "a") as f:
        del f.attrs["frame_interval_s"]
        f["time"] = np.arange(16) * 0.004
    assert read_trajectory(tmp_path / "run.h5").frame_interval_s == pytest.approx(0.004)


def _edit(fn):
    def make(path):
        slide(path, 20.0)
        with h5py.File(path, "a") as f:
            fn(f)
    return make


@pytest.mark.parametrize("make, match", [
    (lambda p: p.write_text("not hdf5"), "cannot read the trajectory"),
    (_edit(lambda f: f.__delitem__("positions")), "missing positions"),
    (_edit(lambda f: f.attrs.__delitem__("bounds_m")), "missing attr bounds_m"),
    (_edit(lambda f: f.attrs.__delitem__("frame_interval_s")), "no frame interval"),
    (_edit(lambda f: f.attrs.__setitem__("frame_interval_s", -1.0)), "must be finite and > 0"),
    (_edit(lambda f: f.attrs.__setitem__("bounds_m", [0.0, 1.0])), r"bounds_m must be \[3, 2\]"),
    (_edit(lambda f: f.attrs.__setitem__("bounds_m", [[1, 0], [0, 1], [0, 1]])), "lo < hi"),
    (_edit(lambda f: (f.__delitem__("positions"), f.create_dataset("positions", data=np.zeros((4, 5))))),
     r"positions must be a float dataset \[frames, n, 3\]"),
    (_edit(lambda f: f["positions"].__setitem__((3, 0, 0), np.nan)), "non-finite positions .* frame 3"),
    (_edit(lambda f: (f.__delitem__("material"), f.create_dataset("material", data=np.ones(3)))),
     r"material must be \[n\] = \[44\]"),
    (_edit(lambda f: (f.__delitem__("particle_type"),
                      f.create_dataset("particle_type", data=np.ones(44)))), "particle_type must be"),
    (_edit(lambda f: (f.attrs.__delitem__("frame_interval_s"),
                      f.create_dataset("time", data=np.arange(16) ** 2 * 1e-3))), "not uniformly"),
])
def test_malformed_runs_are_refused_naming_the_problem(tmp_path, make, match):
    path = tmp_path / "bad.h5"
    make(path)
    with pytest.raises(TrajectoryError, match=match) as err:
        read_trajectory(path)
    assert str(path) in str(err.value)


def test_the_spacing_is_estimated_from_a_lattice():
    x = (np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * S
    assert estimate_spacing(x) == pytest.approx(S)


def test_runs_are_split_by_subfolder_or_by_name(tmp_path):
    for i in range(4):
        slide(tmp_path / f"r{i}.h5", 20.0)
    got = collect([tmp_path], valid=1, test=1)
    assert [(s, p.name) for s, p in got] == [("train", "r0.h5"), ("train", "r1.h5"),
                                             ("valid", "r2.h5"), ("test", "r3.h5")]
    for s in ("train", "valid"):
        (tmp_path / "split" / s).mkdir(parents=True)
        slide(tmp_path / "split" / s / "a.h5", 20.0)
    assert [(s, p.name) for s, p in collect([tmp_path / "split"])] == [("train", "a.h5"),
                                                                       ("valid", "a.h5")]
    with pytest.raises(ValueError, match="lower valid"):
        collect([tmp_path / "r0.h5"], valid=1)


def test_runs_become_a_dataset_without_their_kinematic_particles(tmp_path):
    (tmp_path / "runs").mkdir()
    raw = {phi: slide(tmp_path / "runs" / f"r{phi:02.0f}.h5", phi) for phi in (10.0, 20.0, 40.0)}
    meta = build_from_runs([tmp_path / "runs"], tmp_path / "ds", stride=1, valid=1)
    assert load_metadata(tmp_path / "ds") == json.loads(json.dumps(meta))
    assert meta["frame_interval_s"] == DT and meta["particle_spacing_m"] == pytest.approx(S)
    assert meta["connectivity_radius_m"] == pytest.approx(S * 0.029 / 0.016)
    assert [sc["kinematic_left_out"] for sc in meta["scenes"]] == [8, 8, 8]
    (train_a, train_b), (valid,) = load_split(tmp_path / "ds", "train"), load_split(tmp_path / "ds", "valid")
    np.testing.assert_array_equal(train_a.positions, raw[10.0])
    assert (train_a.friction_angle_deg, train_b.friction_angle_deg) == (10.0, 20.0)
    assert valid.friction_angle_deg == 40.0 and valid.bounds_m.tolist() == BOUNDS
    v = np.concatenate([np.diff(raw[p].astype(np.float64), axis=0).reshape(-1, 3) for p in (10.0, 20.0)])
    np.testing.assert_allclose(meta["vel_mean"], v.mean(0), atol=1e-12)
    assert meta["friction_mean_deg"] == 15.0


def test_runs_the_model_cannot_take_are_refused(tmp_path):
    slide(tmp_path / "a.h5", 20.0, material=False)
    with pytest.raises(ValueError, match="no material dataset.*--friction-deg"):
        build_from_runs([tmp_path / "a.h5"], tmp_path / "ds", valid=0)
    meta = build_from_runs([tmp_path / "a.h5"], tmp_path / "ds", valid=0, friction_deg=33.0)
    assert meta["friction_mean_deg"] == 33.0
    with h5py.File(tmp_path / "a.h5", "a") as f:
        f["material"] = np.linspace(20, 30, 44).astype(np.float32)
    with pytest.raises(ValueError, match="material varies within the run"):
        build_from_runs([tmp_path / "a.h5"], tmp_path / "ds", valid=0)
    with h5py.File(tmp_path / "a.h5", "a") as f:
        del f["material"]
        f["particle_type"][:5] = 5
    with pytest.raises(ValueError, match=r"particle types \[5, 6\]"):
        build_from_runs([tmp_path / "a.h5"], tmp_path / "ds", valid=0, friction_deg=30.0)


def test_training_a_few_steps_on_another_simulators_runs(tmp_path, capsys):
    """The other simulator here is `slide` (examples/dem_column did not exist when this was
    written): its runs go through `minority oracle dataset --from-runs`, train, roll out."""
    from minority.gns.model import ModelConfig
    from minority.gns.rollout import rollout
    from minority.gns.train import TrainConfig, load_checkpoint, train

    runs = tmp_path / "runs"
    runs.mkdir()
    for i, phi in enumerate((5.0, 15.0, 25.0, 20.0)):
        slide(runs / f"slide_{i}.h5", phi, spacing_attr=i % 2 == 0, name=f"slide_{i}")
    assert main(["oracle", "dataset", "--from-runs", str(runs), "--valid", "1", "--test", "1",
                 "-o", str(tmp_path / "ds")]) == 0
    assert "{'train': 2, 'valid': 1, 'test': 1}" in capsys.readouterr().err
    out = tmp_path / "m.pt"
    train(tmp_path / "ds", out, ModelConfig(latent=16, message_passing=2),
          TrainConfig(steps=4, batch=2, val_every=2, val_frames=5, ckpt_every=2), device="cpu")
    model, ckpt = load_checkpoint(out)
    assert ckpt["step"] == 4 and ckpt["stats"]["particle_spacing_m"] == pytest.approx(S, rel=1e-3)
    traj = load_split(tmp_path / "ds", "test")[0]
    pred, _ = rollout(model, traj.positions[:6].astype(np.float64), traj.friction_angle_deg,
                      traj.bounds_m, 4)
    assert pred.shape == (10, 36, 3) and np.isfinite(pred).all()


@pytest.fixture
def dataset(tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    for i, phi in enumerate((10.0, 20.0, 30.0, 40.0)):
        slide(runs / f"s{i}.h5", phi)
    build_from_runs([runs], tmp_path / "ds", valid=1, test=1)
    return tmp_path / "ds"


def test_dataset_npz_dataset_keeps_positions_and_friction(dataset, tmp_path):
    meta = load_metadata(dataset)
    assert main(["oracle", "export-npz", str(dataset), "-o", str(tmp_path / "npz")]) == 0
    theirs = json.loads((tmp_path / "npz" / "metadata.json").read_text())
    assert theirs["dim"] == 3 and theirs["dt"] == DT and theirs["sequence_length"] == 16
    assert theirs["default_connectivity_radius"] == meta["connectivity_radius_m"]
    assert theirs["bounds"] == meta["bounds_m"] and theirs["acc_std"] == meta["acc_std"]
    assert theirs["material_feature_len"] == 1 and theirs["nnode_in"] == 38
    train = load_npz(tmp_path / "npz" / "train.npz")
    pos, ptype, tan_phi = train["s0"]
    assert pos.shape == (16, 36, 3) and ptype.tolist() == [6] * 36
    assert tan_phi == pytest.approx(math.tan(math.radians(10.0)))
    assert main(["oracle", "dataset", "--from-npz", str(tmp_path / "npz"),
                 "-o", str(tmp_path / "back")]) == 0
    back = load_metadata(tmp_path / "back")
    for split in ("train", "valid", "test"):
        for a, b in zip(load_split(dataset, split), load_split(tmp_path / "back", split), strict=True):
            assert a.name == b.name
            np.testing.assert_array_equal(a.positions, b.positions)
            assert b.friction_angle_deg == pytest.approx(a.friction_angle_deg, abs=1e-9)
            np.testing.assert_array_equal(a.bounds_m, b.bounds_m)
    for key in ("frame_interval_s", "connectivity_radius_m", "particle_spacing_m", "vel_std",
                "acc_mean", "friction_std_deg"):
        assert back[key] == pytest.approx(meta[key]), key


def _object(*items):
    out = np.empty(len(items), dtype=object)
    out[:] = items
    return out


def test_a_handmade_npz_in_their_layout_imports(tmp_path):
    """As geoelements/gns documents it: per trajectory (positions, particle_type,
    material_property = tan phi), one int particle type allowed; kinematic particles (3)."""
    src = tmp_path / "theirs"
    src.mkdir()
    trajs = {}
    for i, phi in enumerate((25.0, 35.0)):
        pos = slide(tmp_path / f"r{i}.h5", phi, kinematic=False)
        wall = np.broadcast_to([[0.5, 0.05, 0.01]], (16, 1, 3))
        trajs[f"simulation_{i}"] = _object(np.concatenate([pos, wall], 1),
                                           np.array([6] * 36 + [3]), math.tan(math.radians(phi)))
    np.savez_compressed(src / "train.npz", **trajs)
    np.savez_compressed(src / "valid.npz", simulation_0=_object(pos, 6, math.tan(math.radians(30))))
    (src / "metadata.json").write_text(json.dumps({
        "bounds": BOUNDS, "sequence_length": 15, "default_connectivity_radius": 0.03,
        "dim": 3, "dt": DT, "vel_mean": [0, 0, 0], "vel_std": [1, 1, 1], "acc_mean": [0, 0, 0],
        "acc_std": [1, 1, 1]}))
    meta = import_npz(src, tmp_path / "ds")
    train = load_split(tmp_path / "ds", "train")
    assert [t.positions.shape for t in train] == [(16, 36, 3)] * 2
    assert [t.friction_angle_deg for t in train] == pytest.approx([25.0, 35.0])
    assert meta["connectivity_radius_m"] == 0.03 and meta["particle_spacing_m"] == pytest.approx(S)
    assert meta["acc_std"] != [1, 1, 1]  # recomputed from the positions
    assert load_split(tmp_path / "ds", "valid")[0].friction_angle_deg == pytest.approx(30.0)
    gns_data = np.empty(1, dtype=object)
    gns_data[0] = trajs["simulation_1"]
    np.savez_compressed(src / "train.npz", gns_data=gns_data)
    assert list(load_npz(src / "train.npz")) == ["train_000"]


class _Payload:
    def __reduce__(self):
        return (print, ("code ran",))


def test_an_npz_that_pickles_code_is_refused(tmp_path, capsys):
    with zipfile.ZipFile(tmp_path / "train.npz", "w") as zf, zf.open("evil.npy", "w") as fp:
        np.lib.format.write_array_header_1_0(fp, {"descr": "|O", "fortran_order": False,
                                                  "shape": (1,)})
        pickle.dump(np.array([_Payload()], dtype=object), fp, protocol=3)
    with pytest.raises(NpzError, match="refused: the file pickles builtins.print"):
        load_npz(tmp_path / "train.npz")
    assert "code ran" not in capsys.readouterr().out


@pytest.mark.parametrize("meta, match", [
    ({"dim": 2, "dt": DT, "bounds": BOUNDS}, "dim 2"),
    ({"dim": 3, "bounds": BOUNDS, "default_connectivity_radius": 0.03}, "--frame-interval"),
    ({"dim": 3, "dt": DT, "bounds": BOUNDS}, "--radius"),
])
def test_npz_metadata_the_model_cannot_use_is_refused(tmp_path, meta, match):
    (tmp_path / "metadata.json").write_text(json.dumps(meta))
    np.savez_compressed(tmp_path / "train.npz", a=_object(np.zeros((8, 2, 3)), 6))
    with pytest.raises(NpzError, match=match):
        import_npz(tmp_path, tmp_path / "ds")


@pytest.mark.parametrize("material", ["deg", "none"])
def test_the_friction_angle_exported_in_degrees_or_not_at_all(dataset, tmp_path, material):
    theirs = export_npz(dataset, tmp_path / "npz", material=material)["datasets"]["."]
    item = load_npz(tmp_path / "npz" / "train.npz")["s0"]
    if material == "deg":
        assert len(item) == 3 and item[2] == 10.0 and theirs["nnode_in"] == 38
        meta = import_npz(tmp_path / "npz", tmp_path / "back", material="deg")
        assert [sc["friction_angle_deg"] for sc in meta["scenes"]] == [10.0, 20.0, 30.0, 40.0]
    else:
        assert len(item) == 2 and theirs["nnode_in"] == 37
        with pytest.raises(ValueError, match="no material"):
            import_npz(tmp_path / "npz", tmp_path / "back", material="none")
        meta = import_npz(tmp_path / "npz", tmp_path / "back", material="none", friction_deg=30.0)
        assert meta["friction_std_deg"] == 1.0  # one angle: the feature is 0, its scale 1


def test_cli_refuses_runs_that_are_not_there_or_malformed(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["oracle", "dataset", "--from-runs", str(tmp_path / "none"), "-o", str(tmp_path / "ds")])
    assert exit_.value.code == 2 and "no such file or directory" in capsys.readouterr().err
    slide(tmp_path / "a.h5", 20.0)
    with h5py.File(tmp_path / "a.h5", "a") as f:
        del f.attrs["bounds_m"]
    assert main(["oracle", "dataset", "--from-runs", str(tmp_path / "a.h5"), "--valid", "0",
                 "--radius", "0.03", "-o", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert "minority oracle dataset: error: " in err and "missing attr bounds_m" in err
    assert not (tmp_path / "ds").exists()


def test_training_a_few_steps_on_the_dem_examples_runs(tmp_path, capsys):
    """examples/dem_column (a DEM, not our MPM) writes two small runs; they are packed with
    `oracle dataset --from-runs`, and the GNS trains a few steps on them."""
    import subprocess
    import sys
    from pathlib import Path

    from minority.gns.model import ModelConfig
    from minority.gns.train import TrainConfig, load_checkpoint, train

    run_py = Path(__file__).resolve().parent.parent / "examples" / "dem_column" / "run.py"
    for name, duration in (("dem_a", "0.1"), ("dem_b", "0.12")):
        subprocess.run([sys.executable, str(run_py), "--particles", "300", "--duration",
                        duration, "--no-publish", "--threads", "1", "--out",
                        str(tmp_path / "runs" / f"{name}.h5")], check=True, timeout=600,
                       capture_output=True)
    assert main(["oracle", "dataset", "--from-runs", str(tmp_path / "runs"), "--valid", "1",
                 "-o", str(tmp_path / "ds")]) == 0
    meta = load_metadata(tmp_path / "ds")
    assert [sc["split"] for sc in meta["scenes"]] == ["train", "valid"]
    train(tmp_path / "ds", tmp_path / "m.pt", ModelConfig(latent=16, message_passing=2),
          TrainConfig(steps=3, batch=2, val_every=3, val_frames=3, ckpt_every=3), device="cpu")
    _, ckpt = load_checkpoint(tmp_path / "m.pt")
    assert ckpt["step"] == 3 and ckpt["stats"]["frame_interval_s"] == meta["frame_interval_s"]


# --- what geoelements/gns does with an npz dataset (the expected layout, from their source) ---

GNS_INPUT_SEQUENCE_LENGTH = 6  # gns/train.py: INPUT_SEQUENCE_LENGTH (config data.input_sequence_length)


def gns_read_metadata(path, purpose):
    """gns/reading_utils.py read_metadata(data_path, purpose): the file's [purpose] section
    when it is split by purpose ("train", "rollout"), else all of it."""
    raw = json.loads((path / "metadata.json").read_text())
    return raw[purpose] if isinstance(raw.get(purpose), dict) else raw


def gns_rollout_lengths(metadata, positions):
    """gns/train.py predict() and rollout(): nsteps = metadata["sequence_length"] - 6 (the
    key read with [], so it must be there), or the trajectory's own frame count - 6 where it
    is None; rollout() predicts nsteps frames and subtracts ground_truth = positions[6:].
    Returns (predicted, true) frame counts: their rollout runs only when they are equal."""
    seq = metadata["sequence_length"]
    nsteps = (positions.shape[0] if seq is None else seq) - GNS_INPUT_SEQUENCE_LENGTH
    return nsteps, positions[GNS_INPUT_SEQUENCE_LENGTH:].shape[0]


def gns_wall_features(metadata, x):
    """gns/learned_simulator.py LearnedSimulator._encoder_preprocessor, with boundaries =
    metadata["bounds"] (gns/train.py _get_simulator): distances of x [n, dim] to the lower
    and upper bounds over default_connectivity_radius, clamped to [-1, 1]
    (boundary_clamp_limit 1.0). Returns [n, 2 dim]."""
    b = np.asarray(metadata["bounds"], np.float64)
    r = metadata["default_connectivity_radius"]
    return np.clip(np.concatenate([x - b[:, 0], b[:, 1] - x], axis=1) / r, -1.0, 1.0)


def _move(path, shift, bounds):
    """Shift a run's particles by shift (m) and give it bounds (m)."""
    with h5py.File(path, "a") as f:
        f["positions"][...] = f["positions"][...] + np.asarray(shift, np.float32)
        f.attrs["bounds_m"] = np.asarray(bounds, np.float64)


NARROW = [[0.0, 1.0], [0.0, 0.06], [0.0, 0.5]]  # a channel as wide as the block, m
RAISED = [[0.0, 1.0], [0.0, 0.1], [0.1, 0.6]]  # a floor at z = 0.1 m


@pytest.fixture
def domains(tmp_path):
    """A dataset of three domains: the wide channel (two train scenes and a valid one, 16
    frames), a narrow one (test, 20 frames) and a raised floor (train, 16 frames, the block
    on the floor)."""
    runs = tmp_path / "domain_runs"
    for split, name, phi, frames in (("train", "a_wide", 10.0, 16), ("train", "b_wide", 20.0, 16),
                                     ("train", "c_raised", 25.0, 16), ("valid", "d_wide", 30.0, 16),
                                     ("test", "e_narrow", 40.0, 20)):
        (runs / split).mkdir(parents=True, exist_ok=True)
        pos = slide(runs / split / f"{name}.h5", phi, frames=frames)
        if name == "c_raised":  # the block set down half a spacing above the raised floor
            _move(runs / split / f"{name}.h5", [0, 0, 0.1 + S / 2 - pos[0, :, 2].min()], RAISED)
    _move(runs / "test" / "e_narrow.h5", [0, 0, 0], NARROW)
    build_from_runs([runs], tmp_path / "domain_ds")
    return tmp_path / "domain_ds"


def test_gns_rolls_out_every_trajectory_of_the_export(dataset, domains, tmp_path):
    """The rollout of geoelements/gns compares sequence_length - 6 predicted frames with
    positions[6:]: sequence_length is the frame count (null where the lengths differ)."""
    for ds, out in ((dataset, tmp_path / "one"), (domains, tmp_path / "three")):
        export_npz(ds, out)
        for meta_path in sorted(out.rglob("metadata.json")):
            d = meta_path.parent
            meta = gns_read_metadata(d, "rollout")
            assert "sequence_length" in meta
            for split in ("valid", "test"):
                if (d / f"{split}.npz").is_file():
                    for name, (pos, *_) in load_npz(d / f"{split}.npz").items():
                        predicted, true = gns_rollout_lengths(meta, pos)
                        assert predicted == true > 0, (d, name)
    assert json.loads((tmp_path / "one" / "metadata.json").read_text())["sequence_length"] == 16


def test_an_export_of_trajectories_of_two_lengths_says_null(tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    for i, frames in enumerate((16, 20, 18)):
        slide(runs / f"s{i}.h5", 20.0 + i, frames=frames)
    build_from_runs([runs], tmp_path / "ds", valid=1)
    theirs = export_npz(tmp_path / "ds", tmp_path / "npz")["datasets"]["."]
    assert "sequence_length" in theirs and theirs["sequence_length"] is None
    meta = gns_read_metadata(tmp_path / "npz", "rollout")
    for pos, *_ in load_npz(tmp_path / "npz" / "valid.npz").values():
        assert gns_rollout_lengths(meta, pos) == (12, 12)


def test_gns_sees_the_walls_of_every_trajectory(domains, tmp_path):
    """gns has one `bounds` per dataset: each domain is a dataset of its own, and the wall
    features gns computes from it are those of the scene's own walls (a narrow channel keeps
    its side wall, a raised floor its floor)."""
    theirs = export_npz(domains, tmp_path / "npz")
    assert sorted(theirs["datasets"]) == ["domain_00", "domain_01", "domain_02"]
    meta = load_metadata(domains)
    own = {sc["name"]: (sc["split"], np.asarray(load_bounds(domains, sc["split"], sc["name"])))
           for sc in meta["scenes"]}
    seen = {}
    for d in sorted((tmp_path / "npz").iterdir()):
        m = gns_read_metadata(d, "train")
        for split in ("train", "valid", "test"):
            if not (d / f"{split}.npz").is_file():
                continue
            for name, (pos, *_) in load_npz(d / f"{split}.npz").items():
                assert own[name][0] == split
                expected = gns_wall_features({**m, "bounds": own[name][1].tolist()}, pos[0])
                np.testing.assert_array_equal(gns_wall_features(m, pos[0]), expected)
                seen[name] = (d.name, gns_wall_features(m, pos[0]))
    assert sorted(seen) == ["a_wide", "b_wide", "c_raised", "d_wide", "e_narrow"]
    assert {seen[n][0] for n in ("a_wide", "b_wide", "d_wide")} == {"domain_00"}
    assert seen["e_narrow"][1][:, 4].min() < 1.0  # the side wall y = 0.06 m is within reach
    assert seen["c_raised"][1][:, 2].min() < 1.0  # so is the floor z = 0.1 m
    assert main(["oracle", "dataset", "--from-npz", str(tmp_path / "npz"),
                 "-o", str(tmp_path / "back")]) == 0
    for split in ("train", "valid", "test"):
        for a, b in zip(load_split(domains, split), load_split(tmp_path / "back", split), strict=True):
            assert a.name == b.name
            np.testing.assert_array_equal(a.positions, b.positions)
            np.testing.assert_array_equal(a.bounds_m, b.bounds_m)


def test_an_export_over_an_earlier_one_of_another_layout_is_refused(dataset, domains, tmp_path):
    """Files an export would not replace would be read by gns with the new ones."""
    export_npz(dataset, tmp_path / "npz")
    with pytest.raises(NpzError, match=r"metadata.json, .*train.npz.* of an earlier export"):
        export_npz(domains, tmp_path / "npz")
    assert not (tmp_path / "npz" / "domain_00").exists()
    export_npz(dataset, tmp_path / "npz")  # the same layout again replaces every file


def load_bounds(dataset, split, name):
    with h5py.File(dataset / f"{split}.h5", "r") as f:
        return f[name].attrs["bounds_m"][...]


def test_gns_minority_gns_keeps_every_key(tmp_path):
    """Their dataset as docs/gns_data.md of geoelements/gns lays it out (a raised floor,
    trajectories listed out of name order, statistics of their own making, optional keys),
    imported and exported again: every key of metadata.json, every trajectory's name, order,
    positions, particle types and material_property come back as they were; only our
    "minority" section is added."""
    src = tmp_path / "theirs"
    src.mkdir()
    trajs = {}
    for name, phi in (("simulation_10", 25.0), ("simulation_2", 35.0), ("simulation_3", 30.0)):
        pos = slide(tmp_path / f"{name}.h5", phi, kinematic=False) + np.float32([0, 0, 0.1])
        trajs[name] = _object(pos, np.full(36, 6), np.float64(math.tan(math.radians(phi))))
    np.savez_compressed(src / "train.npz", simulation_10=trajs["simulation_10"],
                        simulation_2=trajs["simulation_2"])
    np.savez_compressed(src / "test.npz", simulation_3=trajs["simulation_3"])
    source = {"bounds": RAISED, "sequence_length": 16, "default_connectivity_radius": 0.03,
              "material_feature_len": 1, "dim": 3, "dt": DT, "nnode_in": 38, "nedge_in": 4,
              "nmessage_passing_steps": 10, "boundary_augment": 1.0,
              "vel_mean": [1e-5, 0.0, -2e-4], "vel_std": [1e-3, 1e-6, 2e-3],
              "acc_mean": [0.0, 0.0, -1e-5], "acc_std": [2e-4, 1e-7, 3e-4]}
    (src / "metadata.json").write_text(json.dumps(source))
    import_npz(src, tmp_path / "ds")
    back = export_npz(tmp_path / "ds", tmp_path / "again")
    again = json.loads((tmp_path / "again" / "metadata.json").read_text())
    assert set(again) - set(source) == {"minority"} and again == back["datasets"]["."]
    assert {k: again[k] for k in source} == source
    for split in ("train", "test"):
        theirs, ours = load_npz(src / f"{split}.npz"), load_npz(tmp_path / "again" / f"{split}.npz")
        assert list(ours) == list(theirs)
        for name, (pos, ptype, prop) in theirs.items():
            np.testing.assert_array_equal(ours[name][0], pos)
            np.testing.assert_array_equal(np.broadcast_to(ours[name][1], (36,)), ptype)
            assert ours[name][2] == pytest.approx(prop, rel=1e-12)


def test_the_test_split_takes_the_rollout_bounds(tmp_path):
    """gns/train.py trains with read_metadata(path, "train") and rolls out (the test split)
    with read_metadata(path, "rollout"): where the file is split by purpose, the test
    trajectories' walls are the rollout section's."""
    src = tmp_path / "theirs"
    src.mkdir()
    pos = slide(tmp_path / "r.h5", 25.0, kinematic=False)
    np.savez_compressed(src / "train.npz", a=_object(pos, 6, 0.5))
    np.savez_compressed(src / "test.npz", b=_object(pos, 6, 0.5))
    common = {"sequence_length": 16, "default_connectivity_radius": 0.03, "dim": 3, "dt": DT,
              "vel_mean": [0, 0, 0], "vel_std": [1, 1, 1], "acc_mean": [0, 0, 0],
              "acc_std": [1, 1, 1]}
    wide = [[0.0, 2.0], [0.0, 0.1], [0.0, 1.0]]
    (src / "metadata.json").write_text(json.dumps({"train": {**common, "bounds": BOUNDS},
                                                   "rollout": {**common, "bounds": wide}}))
    import_npz(src, tmp_path / "ds")
    assert load_split(tmp_path / "ds", "train")[0].bounds_m.tolist() == BOUNDS
    assert load_split(tmp_path / "ds", "test")[0].bounds_m.tolist() == wide
    export_npz(tmp_path / "ds", tmp_path / "again")
    again = json.loads((tmp_path / "again" / "metadata.json").read_text())
    assert set(again) == {"train", "rollout", "minority"}
    assert again["train"] == {**common, "bounds": BOUNDS, "nnode_in": 38, "nedge_in": 4,
                              "material_feature_len": 1}
    assert again["rollout"] == {**again["train"], "bounds": wide}


def test_train_and_test_in_two_domains_are_one_dataset_split_by_purpose(tmp_path):
    """Train and valid scenes in one domain, test scenes in another (docs/gns_data.md of
    geoelements/gns: "test in enlarged domain"): one dataset, its metadata.json split into
    "train" and "rollout", each with its scenes' bounds and frame count."""
    runs = tmp_path / "runs"
    for split, frames in (("train", 16), ("valid", 16), ("test", 20)):
        (runs / split).mkdir(parents=True)
        slide(runs / split / f"{split}_0.h5", 20.0, frames=frames)
    _move(runs / "test" / "test_0.h5", [0, 0, 0], NARROW)
    build_from_runs([runs], tmp_path / "ds")
    theirs = export_npz(tmp_path / "ds", tmp_path / "npz")
    assert list(theirs["datasets"]) == ["."]
    train, rollout = (gns_read_metadata(tmp_path / "npz", p) for p in ("train", "rollout"))
    assert (train["bounds"], train["sequence_length"]) == (BOUNDS, 16)
    assert (rollout["bounds"], rollout["sequence_length"]) == (NARROW, 20)
    (pos, *_), = load_npz(tmp_path / "npz" / "test.npz").values()
    assert gns_rollout_lengths(rollout, pos) == (14, 14)
    import_npz(tmp_path / "npz", tmp_path / "back")
    assert [t.bounds_m.tolist() for s in ("train", "valid", "test")
            for t in load_split(tmp_path / "back", s)] == [BOUNDS, BOUNDS, NARROW]

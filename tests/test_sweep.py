"""The GNS training sweep's runs (minority.sweep): every shipped config's scenes are the ones
the old scene template gave, a tiny sweep writes what `minority sim` writes for its scenes,
resumes where it stopped, and packs into a dataset; a failing scene is a SweepError."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from minority.gns.dataset import build, load_split
from minority.gns.sweep import SweepError, load_config, plan
from minority.protocol.trajectory import SIM_FORMAT, UNITS, FrameWriter, frames_written
from minority.sim.scene import loads_scene
from minority.sweep import frames_due, run_sweep, scene_toml

CONFIGS = Path(__file__).resolve().parent.parent / "gns" / "configs"

# Golden: the scene template the sweep filled before its scenes came from sim.columns
# (gns/configs/column_template.toml of 2026-12), fields in braces filled per scene.
OLD_TEMPLATE = """name = "{name}"
gravity_m_s2 = [0.0, 0.0, -9.81]

[domain]
size_m = [{domain_length_m}, {width_m}, 0.416]
cell_size_m = {cell_size_m}

[particles]
per_cell_per_axis = 2

[material]
density_kg_m3 = 1800.0
youngs_modulus_pa = 2.0e6
poisson_ratio = 0.3
friction_angle_deg = {friction_angle_deg}

[[body]]
shape = "box"
lo_m = [0.0, 0.0, 0.0]
hi_m = [{length_m}, {width_m}, {height_m}]

[boundary]
friction = 0.5
y_min = 0.2
y_max = 0.2
z_max = 0.0

[time]
duration_s = {duration_s}
output_interval_s = {output_interval_s}
cfl = 0.3
"""

# A sweep of four scenes of 24-36 particles at the model's spacing (8x as many in the MPM,
# coarse_grain = 2), 0.04 s each: a few hundred steps.
TINY = """seed = 7
duration_s = 0.04
output_interval_s = 0.01
stride = 2
connectivity_radius_m = 0.029
coarse_grain = 2
coarse_grain_method = "sample"

[geometry]
particle_spacing_m = 0.016
cell_size_m = 0.032
domain_length_m = {domain_length_m}
domain_height_m = 0.416
length_m = [0.048, 0.048]
width_m = [0.064, 0.064]
aspect_ratio = [0.5, 0.8]
max_height_m = 0.064
friction_angle_deg = [25.0, 40.0]
particles = [10, 200]

[splits]
train = 2
valid = 1
test = 1
held_out_aspect_ratio = [[0.95, 1.05]]
held_out_friction_angle_deg = [[33.5, 36.5]]
"""


def old_scene(cfg, p):
    return OLD_TEMPLATE.format(
        cell_size_m=float(cfg.geometry["cell_size_m"]) / cfg.coarse_grain, name=p.name,
        domain_length_m=p.domain_length_m, width_m=p.width_m,
        friction_angle_deg=p.friction_angle_deg, length_m=p.length_m, height_m=p.height_m,
        duration_s=cfg.duration_s, output_interval_s=cfg.output_interval_s)


@pytest.mark.parametrize("config", sorted(p.name for p in CONFIGS.glob("column_sweep*.toml")))
def test_every_shipped_sweep_runs_the_scenes_it_ran_before(config):
    """The same Scene (geometry, material, friction of every face, times, numerics) as the
    old template's, so the runs and the dataset stay the same for the same config and seed."""
    cfg = load_config(CONFIGS / config)
    assert float(cfg.geometry["domain_height_m"]) == 0.416  # the template's fixed height
    for p in plan(cfg):
        new = loads_scene(scene_toml(cfg, p))
        old = loads_scene(old_scene(cfg, p))
        assert dataclasses.replace(new, toml_text="") == dataclasses.replace(old, toml_text="")


def tiny(tmp_path, domain_length_m=0.192):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY.format(domain_length_m=domain_length_m))
    return load_config(path)


def arrays(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f}, {k: v for k, v in f.attrs.items()
                                          if k != "scene_toml"}


def test_a_tiny_sweep_runs_as_minority_sim_resumes_and_packs(tmp_path):
    cfg = tiny(tmp_path)
    runs = tmp_path / "runs"
    log = tmp_path / "log"
    with log.open("w") as out:
        got = run_sweep(cfg, runs, jobs=2, log=out)
    plans = plan(cfg)
    assert [p for p, _ in got] == plans and len(plans) == 4
    assert all(frames_written(h5) == frames_due(cfg) == 5 for _, h5 in got)
    first = {h5.name: arrays(h5) for _, h5 in got}

    # what the sweep ran before: `minority sim` on the scene file, in a process of its own
    p, h5 = got[-1]
    ref = tmp_path / "ref.h5"
    proc = subprocess.run([sys.executable, "-m", "minority", "sim", str(runs / f"{p.name}.toml"),
                           "--out", str(ref), "--threads", "1", "--no-publish", "-q"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    data, attrs = arrays(ref)
    assert attrs["format"] == SIM_FORMAT
    for name, values in data.items():
        np.testing.assert_array_equal(first[h5.name][0][name], values, err_msg=name)
    assert first[h5.name][1].keys() == attrs.keys()

    # resume: complete runs stay as they are; a killed one (1 frame) runs again, the same
    mtimes = {h5: h5.stat().st_mtime_ns for _, h5 in got}
    killed = got[0][1]
    with FrameWriter(killed, 1, fmt=SIM_FORMAT, units=UNITS, attrs={}) as w:
        w.write_frame(0.0, {k: np.zeros((1, 3)) for k in
                            ("positions", "velocities", "displacements")})
    with log.open("w") as out:
        again = run_sweep(cfg, runs, jobs=1, log=out)
    assert again == got and "3 already done, running 1" in log.read_text()
    assert all(h5.stat().st_mtime_ns == mtimes[h5] for _, h5 in got[1:])
    for name, values in arrays(killed)[0].items():
        np.testing.assert_array_equal(first[killed.name][0][name], values, err_msg=name)

    meta = build(got, tmp_path / "data", stride=cfg.stride,
                 connectivity_radius_m=cfg.connectivity_radius_m,
                 coarse_grain=cfg.coarse_grain, coarse_grain_method=cfg.coarse_grain_method,
                 log=open("/dev/null", "w"))
    assert meta["frame_interval_s"] == 0.02 and meta["particle_spacing_m"] == 0.016
    for sc, p in zip(meta["scenes"], plans, strict=True):
        assert (sc["name"], sc["particles"], sc["frames"]) == (p.name, p.particles, 3)
    train = load_split(tmp_path / "data", "train")
    assert [t.name for t in train] == ["train_000", "train_001"]
    for t, p in zip(train, plans[:2], strict=True):  # material is stored as float32
        assert t.friction_angle_deg == pytest.approx(p.friction_angle_deg, rel=1e-6)


def test_a_failing_scene_is_a_sweep_error(tmp_path):
    cfg = tiny(tmp_path, domain_length_m=0.032)  # shorter than the 0.048 m columns
    with pytest.raises(SweepError, match="scene train_000 failed"):
        run_sweep(cfg, tmp_path / "runs", jobs=1, log=open("/dev/null", "w"))

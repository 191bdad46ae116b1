"""The example simulation that was not written for minority (examples/dem_column, a DEM column
collapse): its contact model against textbook results, the collapse's physics (energy never
grows, spheres stay in the channel, the column spreads), its HDF5 trajectory read by the
project's reader, and end to end: publishing through minority.insitu to a render server on
loopback, which renders its frames and logs its chunks and Stats.
Network tests: loopback, a free port each, waits on counts with timeouts."""

from __future__ import annotations

import importlib.util
import io
import json
import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_loopback import wait_until

from minority.protocol import Chunk, Stats
from minority.protocol.log import read_log
from minority.protocol.spec import Spec
from minority.protocol.trajectory import read_trajectory
from minority.render_server.daemon import RenderServer, ServerOptions

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "dem_column"
RUN = "dem-test"


def load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


sys.path.insert(0, str(EXAMPLE))  # run.py imports its sibling dem.py
dem = load("dem", EXAMPLE / "dem.py")
run_py = load("dem_column_run", EXAMPLE / "run.py")

# about 300 spheres of 11.5 mm: the pour and a 0.25 s collapse take a few seconds
SMALL = dem.replace_scene(dem.load_scene(EXAMPLE / "scene.toml").with_particles(300),
                          duration_s=0.25, pour_s=0.4, output_interval_s=0.01)


@pytest.fixture(scope="module")
def collapse(tmp_path_factory):
    """The small column's run, no network: its summary and HDF5 file."""
    out = tmp_path_factory.mktemp("dem") / "run.h5"
    summary = run_py.run(run_py.Options(SMALL, out=out, publish=False, progress=False))
    return summary, out


def free_space(**changes):
    """A wide empty channel without gravity (lengths in m)."""
    return dem.replace_scene(dem.Scene(), channel_m=(0.4, 0.1, 0.1), column_m=(0.05, 0.05, 0.05),
                             diameter_m=0.01, gravity_m_s2=(0.0, 0.0, 0.0), **changes)


def test_a_head_on_collision_rebounds_at_the_restitution_and_keeps_momentum():
    scene = free_space(restitution=0.5)
    d, u = scene.diameter_m, 0.2  # m, m/s each
    x = np.array([[0.2 - d, 0.05, 0.05], [0.2 + d, 0.05, 0.05]])
    sim = dem.Simulation(scene, x, np.array([[u, 0, 0], [-u, 0, 0]]))
    while sim.time_s < 3 * d / u:  # together, in contact, apart
        sim.advance()
    # separation / approach speed: e for the linear spring-dashpot, a little more here as
    # the force is never tensile (the contact ends once the dashpot would pull, Schwager and
    # Poeschel 2007: 0.528 for e = 0.5)
    e = (sim.v[1, 0] - sim.v[0, 0]) / (2 * u)
    assert 0.5 < e < 0.55
    assert np.abs(sim.v.sum(axis=0)).max() < 1e-12  # forces equal and opposite
    assert np.abs(sim.w).max() == 0.0 and np.abs(sim.v[:, 1:]).max() == 0.0


def test_a_sliding_sphere_starts_rolling_at_five_sevenths_of_its_speed():
    """Coulomb friction slows the slide and spins the sphere up until it rolls without
    slipping: then v = 5/7 u and w r = v (solid sphere, no rolling resistance)."""
    scene = dem.replace_scene(free_space(), gravity_m_s2=(0.0, 0.0, -9.81), rolling_friction=0.0,
                              wall_friction=0.5)
    r, u, m = 0.5 * scene.diameter_m, 0.5, scene.mass_kg
    rest = r - m * 9.81 / scene.stiffness_n_m  # resting on the floor's spring
    sim = dem.Simulation(scene, [[0.1, 0.05, rest]], [[u, 0.0, 0.0]])
    slide_s = 2 * u / (7 * 0.5 * 9.81)  # the slip phase: 29 ms
    while sim.time_s < 3 * slide_s:
        sim.advance()
    assert sim.v[0, 0] == pytest.approx(5 / 7 * u, rel=0.01)
    assert sim.w[0, 1] * r == pytest.approx(sim.v[0, 0], rel=0.01)  # rolling, not sliding
    assert abs(sim.x[0, 2] - rest) < 0.01 * r


def test_the_time_step_resolves_a_contact_and_fits_the_frames():
    s = SMALL
    assert s.dt_s <= s.dt_fraction * s.contact_period_s == s.stable_dt_s
    assert s.dt_s * s.steps_per_frame == pytest.approx(s.output_interval_s, rel=1e-12)
    # k_n: the bottom sphere overlaps max_overlap d under the column's weight
    layers = s.column_m[2] / s.diameter_m
    assert layers * s.mass_kg * 9.81 / s.stiffness_n_m == pytest.approx(
        s.max_overlap * s.diameter_m, rel=1e-6)


def test_the_collapse_loses_energy_stays_in_the_channel_and_spreads(collapse):
    summary, out = collapse
    with h5py.File(out, "r") as f:
        x = f["positions"][:]
        energy = f["kinetic_energy"][:] + f["potential_energy"][:] + f["elastic_energy"][:]
        bounds = f.attrs["bounds_m"]
    assert x.shape == (SMALL.frames, SMALL.n, 3) and summary.frames == SMALL.frames
    # frame by frame the energy never grows (dashpots and friction only take it away)
    assert (np.diff(energy) <= 1e-9 * energy[0]).all()
    assert energy[-1] < energy[0] - 0.1 * (energy[0] - energy.min() + 1e-12)
    r = 0.5 * SMALL.diameter_m
    assert (x >= bounds[:, 0] + 0.9 * r).all() and (x <= bounds[:, 1] - 0.9 * r).all()
    runout = np.percentile(x[:, :, 0], 99, axis=1)
    height = np.percentile(x[:, :, 2], 99, axis=1)
    assert runout[-1] > 1.5 * runout[0]  # the front runs out ...
    assert height[-1] < height[0] - 0.5 * r  # ... as the top comes down
    assert (np.diff(runout) > -0.25 * r).all()  # and never retreats
    assert summary.runout_m == pytest.approx((runout[0], runout[-1]), rel=1e-5)


def test_the_trajectory_is_in_the_projects_layout(collapse):
    _, out = collapse
    t = read_trajectory(out)  # what the oracle's dataset builder reads
    assert t.positions.shape == (SMALL.frames, SMALL.n, 3)
    assert t.frame_interval_s == pytest.approx(SMALL.output_interval_s)
    assert np.allclose(t.bounds_m, [[0.0, 0.4], [0.0, 0.04], [0.0, 0.2]])
    assert t.particle_spacing_m == pytest.approx(SMALL.diameter_m)
    assert np.allclose(t.material, math.degrees(math.atan(SMALL.friction)))
    with h5py.File(out, "r") as f:
        assert np.allclose(f["time"][:], np.arange(SMALL.frames) * SMALL.output_interval_s)
        # x - x0 in float64, stored as float32 (m)
        assert np.allclose(f["displacements"][:], f["positions"][:] - f["positions"][0],
                           rtol=0, atol=1e-7)
        assert dem.load_scene_text(f.attrs["scene_toml"]) == SMALL


def test_bad_scenes_and_flags_are_refused_naming_the_problem(tmp_path):
    with pytest.raises(ValueError, match="friction must be a number >= 0"):
        dem.replace_scene(SMALL, friction=-0.1)
    with pytest.raises(ValueError, match="dt_fraction 0.5 is above 0.2"):
        dem.replace_scene(SMALL, dt_fraction=0.5)
    with pytest.raises(ValueError, match="does not fit in the channel"):
        dem.replace_scene(SMALL, column_m=(0.5, 0.04, 0.1))
    bad = tmp_path / "bad.toml"
    bad.write_text("diameter_m = 0.01\nfrction = 0.5\n")
    with pytest.raises(ValueError, match=r"unknown scene keys \['frction'\]"):
        dem.load_scene(bad)
    cli = subprocess.run([sys.executable, str(EXAMPLE / "run.py"), "--particles", "3",
                          "--no-publish"], capture_output=True, text=True, timeout=60)
    assert cli.returncode == 2 and "--particles must be at least 8" in cli.stderr
    helped = subprocess.run([sys.executable, str(EXAMPLE / "run.py"), "--help"],
                            capture_output=True, text=True, timeout=60)
    assert helped.returncode == 0
    for flag in ("--particles", "--duration", "--out", "--run", "--connect", "--spec",
                 "--record", "minority serve"):
        assert flag in helped.stdout


def test_the_example_spec_is_a_valid_spec_of_one_view_with_a_region():
    spec = Spec.from_dict(json.loads((EXAMPLE / "spec.json").read_text()))
    assert spec.run == "dem_column" and [v.name for v in spec.views] == ["heap"]
    assert spec.views[0].field == "displacement" and [r.name for r in spec.regions] == ["front"]


def test_it_publishes_through_insitu_to_a_render_server(server, endpoint, tmp_path):
    """The example next to a render server on loopback: the server serves the spec, the
    example publishes the heap's front at every every_s instant and Stats on their cadence;
    frames are written and the log holds its chunks, Stats and events."""
    spec = Spec.from_dict({
        "version": 2, "run": RUN,
        "regions": [{"name": "front", "lo_m": [0.07, 0.0, 0.0], "hi_m": [0.4, 0.04, 0.2]}],
        "views": [{"name": "heap", "camera": {"position": [0.3, -0.36, 0.2],
                                              "focal_point": [0.19, 0.02, 0.035]},
                   "width": 64, "height": 48, "field": "displacement", "range": [0.0, 0.15],
                   "schedule": [{"every_s": 0.05, "regions": ["front"]}]}]})
    frames_dir, log_path = tmp_path / "frames", tmp_path / "run.mcap"
    daemon = RenderServer(server, ServerOptions(spec, frames_dir, log_path, timeout_s=30.0))
    try:
        scene = dem.replace_scene(SMALL, duration_s=0.2)
        log = io.StringIO()
        summary = run_py.run(run_py.Options(scene, out=tmp_path / "run.h5", run=RUN,
                                            connect=(endpoint,), wait_s=5.0), log=log)
        p = summary.publish
        assert (p["scheduled"], p["sent"], p["dropped"]) == (5, 5, 0)  # t = 0, 0.05, ... 0.2
        assert p["stats_sent"] == p["stats_due"] >= 40  # every 5 ms of simulated time
        # only the front's particles with their displacement (and the rest once, as context)
        assert 0 < p["particles_sent"] < p["particles_total"] + SMALL.n
        assert wait_until(lambda: daemon.finished.is_set())
        s = daemon.summary()
        assert s["chunks"] == 5 and s["frames"] >= 1 and s["view_errors"] == 0
        assert s["lost_in_transit"] == 0
    finally:
        daemon.close()
    pngs = sorted((frames_dir / RUN / "heap").iterdir())
    assert len(pngs) == s["frames"] and pngs[-1].name == f"{summary.steps:06d}.png"
    chunks = [r.decode() for r in read_log(log_path, [f"minority/{RUN}/chunk"])]
    assert len(chunks) == 5 and all(isinstance(c, Chunk) for c in chunks)
    assert chunks[0].spacing_m == pytest.approx(SMALL.diameter_m)
    assert {"positions", "displacement"} <= set(chunks[-1].fields)
    front = chunks[-1].positions[chunks[-1].positions[:, 0] >= 0.07]
    assert len(front) > 0 and chunks[-1].step == summary.steps
    stats = [r.decode() for r in read_log(log_path, [f"minority/{RUN}/stats"])]
    assert len(stats) == p["stats_sent"] and all(isinstance(m, Stats) for m in stats)
    assert all(m.count == SMALL.n for m in stats)
    events = [r.decode() for r in read_log(log_path, [f"minority/{RUN}/event"])]
    kinds = [e.kind for e in events]
    assert "rank_done" in kinds and kinds[-1] == "run_end"
    assert any(e.kind == "run_start" and e.rank == 0 and e.detail["particles"] == SMALL.n
               for e in events)


def test_without_a_server_it_records_and_a_crash_goes_out_as_an_error_event(tmp_path,
                                                                           monkeypatch):
    """No server: the example follows the spec file and records what it would have sent; a
    solver that fails mid-run leaves an `error` event in the record, then the exception."""
    from conftest import free_port

    spec_file = tmp_path / "spec.json"
    spec = json.loads((EXAMPLE / "spec.json").read_text())
    spec["views"][0].update(width=64, height=48)
    spec_file.write_text(json.dumps(spec))
    advance = dem.Simulation.advance

    def failing(self):
        if self.pour_steps and self.step == 150:  # in the collapse, after the pour
            raise FloatingPointError("the solver blew up at step 150")
        advance(self)

    monkeypatch.setattr(dem.Simulation, "advance", failing)
    record = tmp_path / "dem.mcap"
    with pytest.raises(FloatingPointError, match="blew up"):
        run_py.run(run_py.Options(SMALL, connect=(f"tcp/127.0.0.1:{free_port()}",),
                                  spec=spec_file, record=record), log=io.StringIO())
    topics = [r.topic for r in read_log(record)]
    assert topics[0] == "minority/dem_column/spec"
    assert topics.count("minority/dem_column/chunk") == 1  # t = 0 (the next is at 20 ms)
    assert topics.count("minority/dem_column/stats") >= 2
    events = [r.decode() for r in read_log(record, ["minority/dem_column/event"])]
    assert [e.kind for e in events] == ["run_start", "error", "rank_done"]
    assert "FloatingPointError: the solver blew up" in events[1].message

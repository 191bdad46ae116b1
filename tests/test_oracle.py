"""Spec derivation on a synthetic rollout with known events and extent."""

import json
import subprocess
import sys

import numpy as np
import pytest

from minority.gns.export import write_hdf5
from minority.gns.oracle import Oracle, OracleOptions, fit_camera
from minority.protocol import Camera, Spec
from minority.protocol.paraview import read_pvcc
from minority.protocol.projection import in_view, project

DT = 0.005  # s per rollout frame
BOUNDS = np.array([[0.0, 1.0], [0.0, 0.2], [0.0, 0.4]])
START, STOP, TRAVEL = 0.10, 0.50, 0.3  # s, s, m


def collapse(n: int = 600, frames: int = 161, seed: int = 1) -> np.ndarray:
    """A 'column' x in [0, 0.1], z in [0, 0.3]: the particles above z = 0.1 slide +x by TRAVEL
    with a smooth speed bump between START and STOP (s) while dropping to the floor; the base
    never moves. Returns positions [frames, n, 3] (m)."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform([0.0, 0.0, 0.0], [0.1, 0.2, 0.3], (n, 3))
    t = np.arange(frames) * DT
    phase = np.clip((t - START) / (STOP - START), 0, 1)
    s = phase - np.sin(2 * np.pi * phase) / (2 * np.pi)  # 0 -> 1, speed ~ 1 - cos
    pos = np.repeat(x0[None], frames, axis=0)
    top = x0[:, 2] > 0.1
    pos[:, top, 0] += TRAVEL * s[:, None]
    pos[:, top, 2] -= (x0[top, 2] - 0.1)[None] * 0.8 * s[:, None]
    return pos


def step_times(duration_s: float, dt_s: float) -> np.ndarray:
    t = [0.0]
    while t[-1] < duration_s:
        t.append(t[-1] + dt_s)
    return np.array(t)


def rendered(spec: Spec, view, times: np.ndarray) -> np.ndarray:
    return np.array([t for k, t in enumerate(times[1:], 1) if view.wants(k, t, times[k - 1])])


@pytest.fixture(scope="module")
def oracle():
    return Oracle(collapse(), DT, BOUNDS, 0.01, OracleOptions(run="synthetic", frames=90))


def test_events_and_windows_are_found(oracle):
    e = oracle.events
    assert START <= e.onset_s <= START + 0.07  # 5% of the peak speed, soon after the start
    assert e.peak_s == pytest.approx(0.5 * (START + STOP), abs=2 * DT)
    assert STOP - 0.07 <= e.runout_end_s <= STOP + DT
    w = oracle.windows()
    # the fast phase (speed >= half its peak) is the middle half of [START, STOP]
    assert w["runout"][0] == pytest.approx(START + 0.25 * (STOP - START), abs=2 * DT)
    # from the fast phase's first frame (no frame before it, outside the critical window)
    assert w["runout"][0] == pytest.approx(oracle.fast_phase()[0])
    assert w["initiation"][0] <= e.onset_s and w["initiation"][1] >= w["runout"][0]
    lo, hi = oracle.displacement
    assert lo == 0.0 and hi == pytest.approx(np.hypot(TRAVEL, 0.8 * 0.2), rel=0.02)


def test_spec_views_events_range_and_budget(oracle):
    spec = oracle.spec({"rollout": "synthetic"})
    assert [v.name for v in spec.views] == ["side", "top", "aerial"]
    assert [e.name for e in spec.events] == ["failure_onset", "runout_start", "peak_motion",
                                             "runout_end"]
    hi = oracle.displacement[1]
    assert all(v.range == (0.0, pytest.approx(hi * 1.1)) for v in spec.views)
    assert all(v.occlusion_cull for v in spec.views)  # the sim sends what the cameras see
    assert spec.provenance["predicted"]["onset_s"] == oracle.events.onset_s
    times = step_times(0.8, 1.3e-4)  # an MPM-like step
    counts = [len(rendered(spec, v, times)) for v in spec.views]
    assert sum(counts) == spec.budget.frames == 90  # every planned instant renders
    for v in spec.views:  # every frame inside the view's windows
        t = rendered(spec, v, times)
        # inside the view's windows; a window's last instant falls to the step after it
        assert t.min() >= v.t_start_s and t.max() <= v.t_end_s + 1.3e-4
    # cadence where motion is fastest: the runout's densest window is the fastest one
    top = spec.views[1]
    weights = [oracle.weight(w.t_start_s, w.t_end_s) for w in top.schedule]
    assert np.argmin([w.every_s for w in top.schedule]) == np.argmax(weights)
    assert Spec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec


def test_regions_hold_the_moving_particles_and_leave_the_static_base_out(oracle):
    spec = oracle.spec()
    pos, speed = oracle.positions, np.zeros(oracle.positions.shape[:2])
    speed[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=2) / DT
    moving_total = moving_inside = 0
    for k in range(1, len(pos)):
        regions = spec.active_regions(k * DT)
        if regions is None or regions == ():
            continue
        moving = speed[k] > oracle.threshold
        inside = np.zeros(len(pos[k]), bool)
        for r in regions:
            inside |= np.all((pos[k] >= r.lo_m) & (pos[k] <= r.hi_m), axis=1)
        moving_total += moving.sum()
        moving_inside += (moving & inside).sum()
        assert not inside[pos[0][:, 2] < 0.05].any() or k * DT < START  # the base: left out
    assert moving_total > 0 and moving_inside == moving_total


def test_cameras_frame_the_column_and_the_deposit(oracle):
    spec = oracle.spec()
    pos = oracle.positions
    final = pos[int(round(oracle.events.runout_end_s / DT))]
    t0, t1 = oracle.windows()["initiation"]
    column = pos[int(t0 / DT):int(t1 / DT) + 1].reshape(-1, 3)
    for v, pts in zip(spec.views, (column, final, final), strict=True):
        px = project(pts, v.camera, v.width, v.height)
        assert (px >= 0).all() and (px[:, 0] <= v.width).all() and (px[:, 1] <= v.height).all()
        span = px.max(axis=0) - px.min(axis=0)  # tight: it fills most of the image one way
        assert max(span[0] / v.width, span[1] / v.height) > 0.6, v.name


def test_fit_camera_touches_the_frustum():
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.4, 0.1, 0.2])
    fitted = fit_camera(lo, hi, (0, 1, 0), (0, 0, 1), 4 / 3)
    assert isinstance(fitted, Camera)
    cam = Spec.from_dict({"version": 2, "run": "r", "views": [{
        "name": "v", "camera": fitted.to_dict()}]}).views[0].camera
    assert cam == fitted  # a valid spec camera, unchanged by the spec's checks
    corners = np.array([[x, y, z] for x in (0, 0.4) for y in (0, 0.1) for z in (0, 0.2)])
    px = project(corners, cam, 400, 300)
    assert px[:, 0].min() == pytest.approx(0.0, abs=0.5) or px[:, 1].min() == pytest.approx(0.0, abs=0.5)
    # every corner in the frustum, and one on its edge: the box grown by 0.1 % is not
    center = 0.5 * (lo + hi)
    assert in_view(center + (corners - center) * (1.0 - 1e-9), cam, 400, 300).all()
    assert not in_view(center + (corners - center) * 1.001, cam, 400, 300).all()


def test_cli_writes_spec_and_cameras(tmp_path):
    pos = collapse(frames=121)
    write_hdf5(tmp_path / "rollout.h5", pos, DT, attrs={
        "bounds_m": BOUNDS.tolist(), "particle_spacing_m": 0.01, "scene": "synthetic",
        "checkpoint": "none"})
    out = tmp_path / "spec.json"
    proc = subprocess.run([sys.executable, "-m", "minority", "oracle", "spec",
                           str(tmp_path / "rollout.h5"), "-o", str(out), "--run", "r1",
                           "--frames", "60", "--pvcc", str(tmp_path / "cams")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    spec = Spec.load(out)
    assert spec.run == "r1" and spec.budget.frames == 60 and "view side" in proc.stderr
    assert read_pvcc(tmp_path / "cams" / "top.pvcc")[0] == spec.views[1].camera
    bad = subprocess.run([sys.executable, "-m", "minority", "oracle", "spec", str(out)],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "cannot read the rollout" in bad.stderr


def test_preview_contact_sheet(tmp_path):
    from PIL import Image

    from minority.preview import contact_sheet, scheduled_frames

    pos = collapse(frames=121)
    oracle = Oracle(pos, DT, BOUNDS, 0.01, OracleOptions(run="p", frames=30, width=160,
                                                         height=120))
    spec = oracle.spec()
    sheet = contact_sheet(spec, pos, DT, 0.01, columns=4, thumb_width=80, log=open("/dev/null", "w"))
    assert sheet.size == (4 * 80, 3 * (60 + 14) + 14)
    t = np.arange(len(pos)) * DT
    side = scheduled_frames(spec, spec.views[0], t)
    assert side and all(spec.views[0].t_start_s <= t[k] <= spec.views[0].t_end_s for k in side)
    # the first side thumbnail is not blank: particles drawn over the white background
    thumb = np.asarray(sheet.crop((0, 28, 80, 28 + 60)))
    assert (thumb.sum(axis=2) < 600).sum() > 50
    write_hdf5(tmp_path / "r.h5", pos, DT, attrs={"bounds_m": BOUNDS.tolist(),
                                                  "particle_spacing_m": 0.01})
    spec.save(tmp_path / "s.json")
    proc = subprocess.run([sys.executable, "-m", "minority", "oracle", "preview",
                           str(tmp_path / "s.json"), str(tmp_path / "r.h5"), "-o",
                           str(tmp_path / "sheet.png"), "--columns", "3"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert Image.open(tmp_path / "sheet.png").size[0] == 3 * 256


def test_an_mpm_run_reads_as_a_prediction(tmp_path):
    import h5py

    from minority.protocol.trajectory import SIM_FORMAT, read_rollout

    pos = collapse(frames=41)
    with h5py.File(tmp_path / "mpm.h5", "w") as f:
        f["positions"] = pos.astype(np.float32)
        f.attrs.update({"format": SIM_FORMAT, "output_interval_s": 0.02,
                        "bounds_m": BOUNDS, "particle_spacing_m": 0.01,
                        "scene_toml": "[domain]\nsize_m = [1.0, 0.2, 0.4]\n",  # not JSON
                        "units": '{"positions": "m"}', "note": ""})
    r = read_rollout(tmp_path / "mpm.h5")
    assert r["frame_interval_s"] == 0.02 and r["positions"].shape == pos.shape
    assert r["bounds_m"].shape == (3, 2) and r["units"] == {"positions": "m"}
    assert r["scene_toml"].startswith("[domain]") and r["note"] == ""


def test_segments_cut_at_the_fast_phase():
    from minority.gns.oracle import _segments

    def edges(segs):
        return [a for a, _ in segs] + [segs[-1][1]]

    assert edges(_segments(0.0, 1.0, 4, (0.1, 0.4), 0.05)) == pytest.approx([0, 0.1, 0.25, 0.4, 1])
    assert edges(_segments(0.0, 1.0, 4, None)) == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    # the part before is too short for a segment of its own: the fast phase starts the window
    assert edges(_segments(0.0, 1.0, 4, (0.01, 0.4), 0.05)) == pytest.approx(
        [0, 0.4 / 3, 0.8 / 3, 0.4, 1])


@pytest.mark.parametrize("frames", [6, 9, 13])
def test_small_budgets_are_kept(frames):
    spec = Oracle(collapse(), DT, BOUNDS, 0.01,
                  OracleOptions(run="synthetic", frames=frames)).spec()
    times = step_times(0.8, 1.3e-4)
    assert sum(len(rendered(spec, v, times)) for v in spec.views) == frames


def test_too_small_a_budget_is_refused():
    with pytest.raises(ValueError, match="each of the 3 views needs at least 2 frames"):
        OracleOptions(frames=5)


def test_a_rollout_at_rest_still_gives_a_valid_spec():
    still = np.repeat(collapse()[:1], 40, axis=0)
    spec = Oracle(still, DT, BOUNDS, 0.01, OracleOptions(run="still")).spec()
    assert all(v.range[1] > v.range[0] for v in spec.views)


def test_an_early_kinetic_energy_spike_keeps_the_initiation_window_in_order():
    """One particle flung at frame 1 peaks the kinetic energy before the bulk starts to move
    (the speed scale's onset): the initiation window must still run forward."""
    pos = np.repeat(collapse()[:1], 60, axis=0)
    pos[1:, 0, 0] += 0.3  # one of the column's particles jumps 0.3 m between frames 0 and 1
    t = np.arange(60) * DT
    moving = np.clip(t - 0.1, 0.0, None)[:, None] * 0.5  # m: the rest slide from 0.1 s
    pos[:, 1:, 0] += moving
    o = Oracle(pos, DT, BOUNDS, 0.01, OracleOptions(run="spike"))
    ke = o.events.kinetic_m2_s2
    assert np.argmax(ke) * DT < o.events.onset_s  # the case: the spike comes first
    assert o.events.peak_s >= o.events.onset_s  # the flow's peak, not the spike's
    a, b = o.windows()["initiation"]
    assert a < b and a <= o.events.onset_s
    lo, hi = o.fast_phase()
    ra, rb = o.windows()["runout"]
    assert ra <= lo + DT and rb >= hi - DT  # the runout views cover the bulk's motion
    o.spec()  # valid: no window ends before it starts


def test_a_prediction_with_no_flow_keeps_the_frame_budget(tmp_path):
    """A column that only settles (travel under a particle spacing): each view renders the
    run's start and end with every particle (the domain), and the rest of the budget stays
    unplanned for the closed loop; a collapse of the same column is planned as before."""
    pos = collapse()
    x0 = pos[0]
    settle = x0[None] + (pos - x0[None]) * (0.005 / TRAVEL)  # 5 mm of travel at most
    spacing = 0.01
    o = Oracle(settle, DT, BOUNDS, spacing, OracleOptions(run="standing", frames=90))
    assert o.standing()
    spec = o.spec()
    assert spec.provenance["predicted"]["standing"] is True
    assert [r.name for r in spec.regions] == ["domain"]
    assert np.allclose([spec.regions[0].lo_m, spec.regions[0].hi_m], BOUNDS.T)
    times = step_times(o.events.duration_s, 0.001)
    end = o.events.duration_s
    for view in spec.views:
        assert view.wants(0, 0.0, None)  # the start
        assert rendered(spec, view, times) == pytest.approx([end])  # and the end alone
        assert view.range[1] >= spacing  # a readable colormap range at rest
    assert len(spec.views) == 3 and spec.budget.frames == 90
    # the same column collapsing: planned in full, no standing mark
    moving = Oracle(pos, DT, BOUNDS, spacing, OracleOptions(run="standing", frames=90))
    assert not moving.standing()
    assert "standing" not in moving.spec().provenance["predicted"]
    assert sum(len(rendered(moving.spec(), v, times)) for v in moving.spec().views) > 60
    # `minority oracle spec` says so
    write_hdf5(tmp_path / "settle.h5", settle, DT, attrs={
        "bounds_m": BOUNDS.tolist(), "particle_spacing_m": spacing, "scene": "synthetic",
        "checkpoint": "none"})
    proc = subprocess.run([sys.executable, "-m", "minority", "oracle", "spec",
                           str(tmp_path / "settle.h5"), "-o", str(tmp_path / "spec.json"),
                           "--run", "standing"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "no flow predicted" in proc.stderr and "kept for `minority oracle follow`" in proc.stderr
    assert Spec.load(tmp_path / "spec.json").provenance["predicted"]["standing"] is True

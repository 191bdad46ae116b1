"""The ensemble oracle: intervals that cover every member, windows that cover the intervals,
regions that hold every member's movers, the spec's optional fields, the CLI flag."""

import json

import numpy as np
import pytest

from minority.gns.ensemble import (
    EnsembleOptions,
    band,
    deposit_spread,
    friction_offsets,
    perturbed_starts,
)
from minority.gns.events import EVENT_NAMES, event_times, find_events, moving_points
from minority.gns.oracle import Oracle, OracleOptions
from minority.protocol.errors import SpecError
from minority.protocol.spec import Spec, inside_mask

DT = 0.005  # s per frame
BOUNDS = np.array([[0.0, 1.0], [0.0, 0.2], [0.0, 0.4]])


def collapse(start: float, stop: float, travel: float, n: int = 500, frames: int = 161,
             seed: int = 1) -> np.ndarray:
    """A column x in [0, 0.1], z in [0, 0.3] whose particles above z = 0.1 slide +x by
    `travel` (m) with a smooth speed bump from `start` to `stop` (s); positions
    [frames, n, 3] m."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform([0.0, 0.0, 0.0], [0.1, 0.2, 0.3], (n, 3))
    t = np.arange(frames) * DT
    phase = np.clip((t - start) / (stop - start), 0, 1)
    s = phase - np.sin(2 * np.pi * phase) / (2 * np.pi)
    pos = np.repeat(x0[None], frames, axis=0)
    top = x0[:, 2] > 0.1
    pos[:, top, 0] += travel * s[:, None]
    pos[:, top, 2] -= (x0[top, 2] - 0.1)[None] * 0.8 * s[:, None]
    return pos


# the nominal, an early and short member, a late and long one
MEMBERS = [collapse(0.10, 0.50, 0.30), collapse(0.07, 0.44, 0.25), collapse(0.14, 0.58, 0.50)]


@pytest.fixture(scope="module")
def ensemble():
    o = Oracle(MEMBERS[0], DT, BOUNDS, 0.01, OracleOptions(run="ens", frames=90,
                                                           interval_widen=0.5),
               members=MEMBERS[1:])
    return o, o.spec()


def test_each_interval_covers_every_members_event_time(ensemble):
    o, spec = ensemble
    times = [event_times(find_events(m, DT), DT) for m in MEMBERS]
    assert [e.name for e in spec.events] == list(EVENT_NAMES)
    for e in spec.events:
        member_times = [t[e.name] for t in times]
        assert e.earliest_s <= min(member_times) and max(member_times) <= e.latest_s
        assert e.time_s == times[0][e.name]  # the nominal member's, as a single oracle's
        # widened by half the members' range and a frame on each side, within the rollout
        lo, hi = min(member_times), max(member_times)
        w = 0.5 * (hi - lo) + DT
        assert e.earliest_s == pytest.approx(max(lo - w, 0.0))
        assert e.latest_s == pytest.approx(min(hi + w, o.events.duration_s))
    assert spec.events[0].latest_s - spec.events[0].earliest_s > 0.05  # the members differ


def test_windows_cover_the_intervals(ensemble):
    _, spec = ensemble
    ev = {e.name: e for e in spec.events}
    phases = {"side": ("failure_onset", "peak_motion"),
              "top": ("runout_start", "runout_end"), "aerial": ("runout_start", "runout_end")}
    for view in spec.views:
        first, last = phases[view.name]
        assert view.schedule[0].t_start_s <= ev[first].earliest_s
        assert view.schedule[-1].t_end_s >= ev[last].latest_s
        # the windows tile the view's span: no gap a due frame could fall into
        for a, b in zip(view.schedule[:-1], view.schedule[1:], strict=True):
            assert a.t_end_s == pytest.approx(b.t_start_s)


def test_cadence_spends_frames_over_every_members_fast_phase(ensemble):
    o, spec = ensemble
    single = Oracle(MEMBERS[0], DT, BOUNDS, 0.01, OracleOptions(run="one", frames=90)).spec()
    late = MEMBERS[2]  # its runout lasts past the nominal's
    late_end = o.each[2]._own_windows()["runout"][1]  # s, its rest (plus a frame)

    def instants(s):
        view = next(v for v in s.views if v.name == "top")
        return [w.t_start_s + k * w.every_s for w in view.schedule
                for k in range(round((w.t_end_s - w.t_start_s) / w.every_s))]
    assert late.shape == MEMBERS[0].shape
    assert max(instants(spec)) > max(instants(single))
    assert max(instants(spec)) <= late_end + DT


def test_regions_hold_every_members_moving_particles(ensemble):
    o, spec = ensemble
    for view in spec.views:
        for w in view.schedule:
            boxes = tuple(spec.region(n) for n in w.regions)
            for member in o.each:
                pts = moving_points(member.positions, DT, w.t_start_s, w.t_end_s,
                                    member.threshold)
                if pts is not None:
                    assert inside_mask(pts, boxes).all(), (view.name, w.t_start_s)


def test_the_nominal_alone_would_miss_the_late_member(ensemble):
    """The check above can fail: the single rollout's regions leave the long member's front
    out."""
    single = Oracle(MEMBERS[0], DT, BOUNDS, 0.01, OracleOptions(run="one", frames=90)).spec()
    late = Oracle(MEMBERS[2], DT, BOUNDS, 0.01)
    missed = 0
    for view in single.views:
        for w in view.schedule:
            pts = moving_points(late.positions, DT, w.t_start_s, w.t_end_s, late.threshold)
            boxes = tuple(single.region(n) for n in w.regions)
            missed += 0 if pts is None else int((~inside_mask(pts, boxes)).sum())
    assert missed > 0


def test_deposit_spread_is_per_member_with_its_band(ensemble):
    _, spec = ensemble
    d = spec.deposit
    fronts = [float(np.quantile(m[-1, :, 0], 0.99)) for m in MEMBERS]
    assert list(d.runout_m.members) == pytest.approx(fronts)
    for s in (d.runout_m, d.height_m, d.displacement_max_m):
        assert len(s.members) == 3 and s.low <= min(s.members) <= max(s.members) <= s.high
    assert d.runout_m.high - d.runout_m.low == pytest.approx(2 * (max(fronts) - min(fronts)))
    # the colormap covers the member that travels farthest
    assert spec.views[0].range[1] >= d.displacement_max_m.members[2]


def test_a_single_rollout_spec_has_no_interval_or_spread():
    spec = Oracle(MEMBERS[0], DT, BOUNDS, 0.01, OracleOptions(run="one", frames=90)).spec()
    d = spec.to_dict()
    assert "deposit" not in d and all(set(e) == {"name", "time_s", "tolerance_s"}
                                      for e in d["events"])
    assert spec.deposit is None and all(e.interval_s is None for e in spec.events)


def test_old_specs_round_trip_unchanged_and_new_fields_round_trip(ensemble):
    from conftest import make_spec

    old = make_spec().to_dict()
    old["events"] = [{"name": "peak_motion", "time_s": 0.2, "tolerance_s": 0.02}]
    assert Spec.from_dict(json.loads(json.dumps(old))).to_dict() == old
    _, spec = ensemble
    again = Spec.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert again == spec and again.to_dict() == spec.to_dict()


@pytest.mark.parametrize("change, message", [
    (lambda d: d["events"][0].pop("latest_s"), "earliest_s and latest_s come together"),
    (lambda d: d["events"][0].update(earliest_s=0.5, latest_s=0.1), "exceeds latest_s"),
    (lambda d: d["deposit"]["height_m"].update(low=1.0, high=0.5), "deposit.height_m: low"),
    (lambda d: d["deposit"]["runout_m"].update(members=[0.1]), "one value per member"),
])
def test_bad_intervals_are_refused_by_name(ensemble, change, message):
    d = json.loads(json.dumps(ensemble[1].to_dict()))
    change(d)
    with pytest.raises(SpecError, match=message):
        Spec.from_dict(d)


def test_members_must_match_the_prediction():
    with pytest.raises(ValueError, match="member 1 is"):
        Oracle(MEMBERS[0], DT, BOUNDS, 0.01, members=[MEMBERS[1][:100]])


def test_perturbed_starts_keep_the_history_velocities():
    rng = np.random.default_rng(0)
    history = np.cumsum(rng.normal(0, 1e-3, (6, 50, 3)), axis=0)
    starts = perturbed_starts(history, 30.0, 0.016, EnsembleOptions(members=5, perturb="both"))
    assert starts[0].friction_deg == 30.0 and np.array_equal(starts[0].history, history)
    jittered = [s for s in starts[1:] if s.label["jitter_m"] > 0]
    assert len(jittered) == 2
    for s in jittered:
        assert np.allclose(np.diff(s.history, axis=0), np.diff(history, axis=0))
        assert 0.0005 < np.std(s.history - history) < 0.003  # 0.1 spacing of 0.016 m
    assert sorted(s.friction_deg for s in starts[1:] if s.label["friction_offset_deg"]) \
        == [28.0, 32.0]
    # "both" with 2k + 1 members is "jitter" and "friction" with k + 1 each
    j = perturbed_starts(history, 30.0, 0.016, EnsembleOptions(members=3, perturb="jitter"))
    f = perturbed_starts(history, 30.0, 0.016, EnsembleOptions(members=3, perturb="friction"))
    assert [np.array_equal(a.history, b.history) for a, b in zip(j[1:], starts[1::2],
                                                                  strict=True)] == [True, True]
    assert [a.friction_deg for a in f[1:]] == [b.friction_deg for b in starts[2::2]]
    assert friction_offsets(4, 2.0) == [-1.0, 1.0, -2.0, 2.0]
    with pytest.raises(ValueError, match="perturbation 'seeds'"):
        EnsembleOptions(perturb="seeds")


def test_band_and_spread():
    assert band([1.0, 2.0, 4.0], 0.5, 0.1) == pytest.approx((-0.6, 5.6))
    assert band([1.0, 2.0], 1.0, 0.0, lo=0.5, hi=2.5) == (0.5, 2.5)
    spread = deposit_spread(MEMBERS, 0.0)
    assert spread["runout_m"]["low"] == min(spread["runout_m"]["members"])


def test_cli_spec_ensemble_on_a_tiny_rollout(tmp_path, capsys):
    """--ensemble 3 rolls the rollout's checkpoint from perturbed starts and writes a spec
    with intervals and a deposit spread; without it the spec is the single rollout's."""
    import torch

    from minority.cli import main
    from minority.gns.export import write_hdf5
    from minority.gns.model import GNS, ModelConfig
    from minority.gns.rollout import rollout

    stats = {"vel_mean": [0.0] * 3, "vel_std": [1e-3] * 3, "acc_mean": [0.0, 0.0, -1e-4],
             "acc_std": [1e-4] * 3, "friction_mean_deg": 30.0, "friction_std_deg": 5.0,
             "connectivity_radius_m": 0.029, "particle_spacing_m": 0.016,
             "frame_interval_s": DT}
    torch.manual_seed(0)
    model = GNS(ModelConfig(latent=8, mlp_layers=1, message_passing=1), stats).eval()
    ckpt = tmp_path / "tiny.pt"
    torch.save({"format": "minority-gns-checkpoint/1", "model_config": model.config.to_dict(),
                "stats": stats, "state_dict": model.state_dict(), "step": 0,
                "history": []}, ckpt)
    g = (np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5)
    x0 = g * 0.016 + [0.0, 0.0, 0.0]
    history = np.stack([x0 + [0.0, 0.0, -1e-4 * k * k] for k in range(6)])
    bounds = np.array([[0.0, 0.3], [0.0, 0.064], [0.0, 0.1]])
    pos, _ = rollout(model, history, 30.0, bounds, 30)
    write_hdf5(tmp_path / "rollout.h5", pos, DT,
               attrs={"scene": "none", "checkpoint": str(ckpt), "friction_angle_deg": 30.0,
                      "bounds_m": bounds, "particle_spacing_m": 0.016})
    out = tmp_path / "spec.json"
    assert main(["oracle", "spec", str(tmp_path / "rollout.h5"), "--run", "tiny", "-o",
                 str(out), "--ensemble", "3", "--widen", "0.5", "--frames", "12",
                 "--threads", "1"]) == 0
    err = capsys.readouterr().err
    spec = Spec.load(out)
    assert spec.deposit is not None and len(spec.deposit.runout_m.members) == 3
    assert all(e.earliest_s <= e.time_s <= e.latest_s for e in spec.events)
    assert spec.provenance["ensemble"]["members"] == 3 and "ensemble of 3" in err
    assert main(["oracle", "spec", str(tmp_path / "rollout.h5"), "--run", "tiny", "-o",
                 str(tmp_path / "one.json"), "--frames", "12"]) == 0
    assert Spec.load(tmp_path / "one.json").deposit is None
    # a rollout that names no checkpoint cannot make an ensemble: bad input, no spec
    write_hdf5(tmp_path / "mpm.h5", pos, DT, attrs={"bounds_m": bounds,
                                                      "particle_spacing_m": 0.016})
    assert main(["oracle", "spec", str(tmp_path / "mpm.h5"), "--run", "tiny", "-o",
                 str(tmp_path / "bad.json"), "--ensemble", "2"]) == 2
    assert "--ensemble needs a GNS rollout" in capsys.readouterr().err
    assert not (tmp_path / "bad.json").exists()
    with pytest.raises(SystemExit):
        main(["oracle", "spec", str(tmp_path / "rollout.h5"), "--ensemble", "0"])


def test_score_says_whether_the_run_fell_inside_the_intervals(tmp_path):
    from test_score import make_spec as scored_spec
    from test_score import write_log

    from minority.score import load_run, markdown, score

    write_log(tmp_path / "run.mcap", np.linspace(0.22, 0.38, 20))
    d = scored_spec().to_dict()
    d["events"][0].update(earliest_s=0.20, latest_s=0.25)  # the run's onset is ~0.13 s
    d["events"][1].update(earliest_s=0.28, latest_s=0.40)  # its peak ~0.30 s
    spread = {"low": 0.25, "high": 0.35, "members": [0.3]}
    d["deposit"] = {"runout_m": spread, "height_m": spread, "displacement_max_m": spread}
    result = score(Spec.from_dict(d), load_run(tmp_path / "run.mcap"))
    ev = {e["event"]: e for e in result["events"]}
    assert not ev["failure_onset"]["within_interval"] and ev["peak_motion"]["within_interval"]
    assert "within_interval" not in ev["runout_end"]  # no interval stated
    assert result["displacement_band_m"] == {"band": [0.25, 0.35], "within": True}
    text = markdown(result)
    assert "inside the ensemble's interval" in text and "yes (0.280-0.400)" in text
    assert "the ensemble's band 0.250-0.350 m: inside" in text
    # a single oracle's spec scores as before: no interval column
    plain = score(scored_spec(), load_run(tmp_path / "run.mcap"))
    assert "displacement_band_m" not in plain and "ensemble" not in markdown(plain)

"""The oracle's score on a hand-made log with a known run."""

import json

import numpy as np
import pytest

from minority.protocol import Chunk, Frame, Spec, Stats
from minority.protocol.flow import histogram_quantile, moving_count
from minority.protocol.log import LogWriter
from minority.protocol.messages import SPEED_BINS, speed_histogram
from minority.score import load_run, markdown, score

RUN = "scored"
N_RANK = 500  # particles per rank, 2 ranks
STATS_DT = 0.01  # s
PNG = (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x04\x00\x00\x00\x03"
       b"\x08\x02\x00\x00\x00")


def speed_profile(t: float) -> float:
    """Peak speed (m/s): a bump between 0.1 and 0.5 s, 2 m/s at 0.3 s."""
    phase = np.clip((t - 0.1) / 0.4, 0, 1)
    return float(1.0 - np.cos(2 * np.pi * phase))


def make_spec(views=1) -> Spec:
    cam = {"position": [0, -1, 0], "focal_point": [0, 0, 0]}
    return Spec.from_dict({
        "version": 2, "run": RUN,
        "views": [{"name": f"v{i}", "camera": cam, "schedule": [{"every_steps": 1}]}
                  for i in range(views)],
        "events": [{"name": "failure_onset", "time_s": 0.13},
                   {"name": "peak_motion", "time_s": 0.36},  # 20% late
                   {"name": "runout_end", "time_s": 0.48}],
        "provenance": {"predicted": {"displacement_range_m": [0.0, 0.33]}}})


def write_log(path, frame_times, chunk_particles=100, other_run=False):
    rng = np.random.default_rng(0)
    with LogWriter(path) as log:
        ns = 1
        if other_run:  # another run recorded in the same log: fast, and never scored
            hist = speed_histogram(np.full(N_RANK, 9.0))
            for k in range(5):
                log.write(Stats("other", 0, k, 0.01 * k, N_RANK, 81.0 * N_RANK, 9.0, 5.0, True,
                                hist, [0] * SPEED_BINS), log_ns=ns)
                log.write(Frame("other", "v0", k, 0.01 * k, 4, 3, PNG), log_ns=ns + 1)
                ns += 2
        for k, t in enumerate(np.arange(0, 0.8001, STATS_DT)):
            for rank in range(2):
                # half of each rank's particles move at the profile's speed (outside the
                # regions on rank 1 between 0.2 and 0.3 s), the rest rest
                v = np.zeros(N_RANK)
                v[: N_RANK // 2] = speed_profile(t) * rng.uniform(0.9, 1.0, N_RANK // 2)
                inside = np.ones(N_RANK, bool)
                if rank == 1 and 0.2 <= t <= 0.3:
                    inside[:10] = False
                h_in, h_out = speed_histogram(v[inside]), speed_histogram(v[~inside])
                log.write(Stats(RUN, rank, k, float(t), N_RANK, float((v * v).sum()),
                                float(v.max()), 0.3 * min(t / 0.5, 1.0), 0.05 <= t <= 0.6,
                                h_in, h_out), log_ns=ns)
                ns += 1
        for step, t in enumerate(frame_times):
            for rank in range(2):
                pos = rng.uniform(0, 1, (chunk_particles, 3)).astype(np.float32)
                disp = np.zeros((chunk_particles, 3), np.float32)
                log.write(Chunk(RUN, step, float(t), rank, 2, 0.01, ((0, 0, 0), (1, 1, 1)),
                                {"positions": pos, "displacement": disp}), log_ns=ns)
                ns += 1
            log.write(Frame(RUN, "v0", step, float(t), 4, 3, PNG), log_ns=ns)
            ns += 1


def test_the_histogram_quantile_equals_a_walk_up_the_cumulative_counts():
    """Against a plain per-row reading: the bin where the cumulative count reaches q of the
    total, log-interpolated inside it; the lowest bin and an empty row read as rest."""
    from minority.protocol.messages import SPEED_BINS, SPEED_EDGES_M_S

    edges = np.asarray(SPEED_EDGES_M_S)
    lo, hi = np.r_[edges[0] * 0.1, edges], np.r_[edges, edges[-1] * 10]
    rng = np.random.default_rng(3)
    hist = rng.integers(0, 5, (40, SPEED_BINS)) * (rng.random((40, SPEED_BINS)) < 0.3)
    hist[0] = 0
    hist[1, 0] = 7  # all at rest
    for q in (0.5, 0.95):
        want = []
        for row in hist:
            cum, total = np.cumsum(row), row.sum()
            i = int(np.searchsorted(cum, q * total)) if total else 0
            below = cum[i - 1] if i else 0
            frac = (q * total - below) / max(row[i], 1)
            want.append(lo[i] * (hi[i] / lo[i]) ** frac if i and total else 0.0)
        assert np.allclose(histogram_quantile(hist, q), want, rtol=1e-12, atol=0)


def test_histogram_quantile_and_moving_count():
    v = np.geomspace(0.01, 1.0, 1001)
    h = np.array([speed_histogram(v)])
    assert histogram_quantile(h, 0.5)[0] == pytest.approx(0.1, rel=0.13)  # a bin is 26%
    assert moving_count(h, 0.1)[0] == pytest.approx(500, abs=60)
    assert h.shape == (1, SPEED_BINS)


def test_score_of_a_known_run(tmp_path):
    frames = np.linspace(0.22, 0.38, 20)  # all inside the fast phase
    write_log(tmp_path / "run.mcap", frames)
    run = load_run(tmp_path / "run.mcap")
    assert run.particles == 2 * N_RANK and len(run.time_s) == 81
    assert run.max_displacement_m == pytest.approx(0.3)
    result = score(make_spec(), run)
    ev = {e["event"]: e for e in result["events"]}
    # speed >= 5% of the peak from ~0.13 s; the fast phase (>= half) is 0.2-0.4 s
    assert ev["failure_onset"]["actual_s"] == pytest.approx(0.13, abs=0.015)
    assert ev["peak_motion"]["actual_s"] == pytest.approx(0.30, abs=0.011)
    assert not ev["peak_motion"]["within_tolerance"] and ev["failure_onset"]["within_tolerance"]
    assert ev["peak_motion"]["tolerance_s"] == pytest.approx(0.1 * ev["peak_motion"]["actual_s"])
    assert ev["failure_onset"]["tolerance_s"] == pytest.approx(0.013, abs=0.0015)
    (a, b), = result["critical_windows_s"]
    assert a == pytest.approx(0.2, abs=0.011) and b == pytest.approx(0.4, abs=0.011)
    assert result["displacement_max_m"]["relative_error"] == pytest.approx(0.1)
    # moving particles outside the regions: 10 of 500 on rank 1 at the stats steps in 0.2-0.3 s
    open_steps = [t for t in run.time_s if 0.05 <= t <= 0.6]
    moving = sum(500 for t in open_steps if speed_profile(t) * 0.9 > 0.05 * 2.0 * 0.98)
    outside = 10 * sum(1 for t in open_steps if 0.2 <= t <= 0.3 + 1e-9)
    assert result["roi_moving_fraction"] == pytest.approx(1 - outside / moving, abs=0.002)
    f = result["frames"]
    assert f["oracle"] == 20 and f["oracle_in_critical"] == 20
    # 20 frames evenly over 0.8 s: those in [0.2, 0.4] (a quarter of the run)
    assert f["fixed_cadence_in_critical"] == 5 and f["ratio"] == pytest.approx(4.0)
    b = result["bytes"]
    per_particle = 12 + 12  # positions and displacement, float32 x 3 each
    assert b["every_particle_at_rendered_steps"] == 20 * 1000 * per_particle
    assert b["sent"] > 20 * 200 * per_particle  # payload headers on top
    assert 0.2 < b["fraction"] < 0.24  # 200 of 1000 particles, plus the chunk headers
    assert b["fixed_cadence"] == 20 * 1000 * per_particle
    text = markdown(result)
    assert "ratio 4.00x" in text and "| peak_motion |" in text


def test_no_stats_is_a_clear_error(tmp_path):
    write_log_empty = tmp_path / "empty.mcap"
    with LogWriter(write_log_empty):
        pass
    with pytest.raises(ValueError, match="no stats records"):
        load_run(write_log_empty)


def test_cli_report_score(tmp_path, capsys):
    from minority.cli import main

    write_log(tmp_path / "run.mcap", np.linspace(0.22, 0.38, 20), other_run=True)
    make_spec().save(tmp_path / "spec.json")
    assert main(["report", "score", str(tmp_path / "spec.json"), str(tmp_path / "run.mcap"),
                 "--out", str(tmp_path / "s")]) == 0
    assert "| peak_motion | 0.360 |" in capsys.readouterr().out
    assert (tmp_path / "s" / "score.json").is_file()
    # the spec's run only: the same score as a log without the other run
    scored = json.loads((tmp_path / "s" / "score.json").read_text())
    write_log(tmp_path / "alone.mcap", np.linspace(0.22, 0.38, 20))
    alone = json.loads(json.dumps(score(make_spec(), load_run(tmp_path / "alone.mcap"))))
    assert scored == alone and scored["frames"]["oracle"] == 20
    with pytest.raises(ValueError, match="no stats records of run 'nobody'"):
        load_run(tmp_path / "run.mcap", "nobody")
    with pytest.raises(SystemExit) as usage:  # argparse: the usage, exit status 2
        main(["report", "score", str(tmp_path / "spec.json")])
    assert usage.value.code == 2 and "usage: minority report score" in capsys.readouterr().err
    assert main(["report", "score", str(tmp_path / "spec.json"), str(tmp_path / "no.mcap")]) == 2
    assert "no.mcap: no such file" in capsys.readouterr().err


def test_an_indexed_log_and_the_same_log_cut_short_score_the_same(tmp_path):
    write_log(tmp_path / "run.mcap", np.linspace(0.22, 0.38, 20), other_run=True)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((tmp_path / "run.mcap").read_bytes()[:-20])  # no footer: read front to back
    said = []
    whole, short = load_run(tmp_path / "run.mcap", RUN), load_run(cut, RUN, notice=said.append)
    a, b = score(make_spec(), whole), score(make_spec(), short)
    assert a.pop("log") == {"complete": True, "notes": []}
    assert b.pop("log")["complete"] is False and len(said) == 1
    assert json.dumps(a, default=float) == json.dumps(b, default=float)


def test_the_oracle_loop_bench_reads_the_errors_of_a_known_run(tmp_path):
    """bench.oracle_loop's line on the hand-made run: the peak 20 % late, the displacement
    10 % over; the errors relative to the actual times."""
    from bench.oracle_loop import event_errors

    write_log(tmp_path / "run.mcap", np.linspace(0.22, 0.38, 20))
    result = score(make_spec(), load_run(tmp_path / "run.mcap"))
    err = event_errors(result)
    actual = {e["event"]: e["actual_s"] for e in result["events"]}
    assert err["event_errors"]["peak_motion"] == pytest.approx(0.36 / actual["peak_motion"] - 1,
                                                              abs=1e-4)
    assert err["event_errors"]["peak_motion"] == pytest.approx(0.2, abs=0.05)
    assert err["event_error_max"] == max(abs(v) for v in err["event_errors"].values())
    assert set(err["event_errors"]) == {"failure_onset", "peak_motion", "runout_end"}
    assert err["displacement_error"] == pytest.approx(0.1)

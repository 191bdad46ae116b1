"""`minority report`: exact numbers from a hand-made log, the CLI, the plots, bad input."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from conftest import make_png, make_spec

from minority.cli import main
from minority.protocol import Chunk, Event, EventKind, Frame, Timing
from minority.protocol.costs import byte_summary, step_accounting, timing_table, total_particles
from minority.protocol.log import LogWriter
from minority.protocol.runlog import RunLogError
from minority.report import load_run, markdown, plots

RUN = "rep"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PARTICLES = 1_000_000  # the run's total, as sim rank 0's run_start event says
PER_CHUNK = 50  # particles per logged chunk (culled to regions of interest)
PARTICLE_BYTES = 16  # positions [n, 3] float32 + displacement_magnitude [n] float32
# step -> (receive s, setup s, {view: render s}, bytes received, ranks received of 2)
STEPS = {20: (0.010, 0.002, {"side": 0.004, "top": 0.004}, 2_000_000, 2),
         40: (0.020, 0.004, {"side": 0.006, "top": 0.010}, 1_000_000, 1),  # incomplete
         60: (0.030, 0.006, {"side": 0.008, "top": 0.016}, 2_000_000, 2)}
CHUNK_STEPS = {20: (0, 1), 40: (0,), 60: (0, 1), 80: (0, 1)}  # step 80: skipped by the server


def chunk(step: int, rank: int, n: int = PER_CHUNK, run: str = RUN) -> Chunk:
    rng = np.random.default_rng(step * 10 + rank)
    return Chunk(run, step, step * 1e-4, rank, 2, 0.005, ((0.0, 0.0, 0.0), (1.0, 0.5, 0.5)),
                 {"positions": rng.random((n, 3), dtype=np.float32),
                  "displacement_magnitude": rng.random(n, dtype=np.float32)})


def write_log(path, *, events: bool = True, timings: bool = True, spec: bool = False,
              run: str = RUN):
    with LogWriter(path) as w:
        if spec:
            w.write(make_spec(run))
        if events:
            w.write(Event(run, EventKind.RUN_START, -1, "render server up, 2 views"))
            w.write(Event(run, EventKind.RUN_START, 0, "sim on 2 ranks",
                          {"ranks": 2, "particles": PARTICLES}))
        for step, ranks in CHUNK_STEPS.items():
            for rank in ranks:
                w.write(chunk(step, rank, run=run))
        if timings:
            for step, (receive, setup, renders, nbytes, got) in STEPS.items():
                for view, render in renders.items():
                    if (step, view) != (60, "top"):  # its frame was not logged
                        w.write(Frame(run, view, step, step * 1e-4, 4, 3, make_png()))
                    w.write(Timing(run, step, view, step * 1e-4, receive, setup, render, nbytes,
                                   PER_CHUNK * got, 2, got, got < 2))
        if events:
            w.write(Event(run, EventKind.ERROR, -1, "view 'x' needs field 'y'", {"errors": 1}))
            w.write(Event(run, EventKind.RANK_DONE, 0, "rank 0 done",
                          {"particles": 600_000, "scheduled": 4, "sent": 4, "dropped": 0}))
            w.write(Event(run, EventKind.RANK_DONE, 1, "rank 1 done",
                          {"particles": 400_000, "scheduled": 4, "sent": 3, "dropped": 1}))
            w.write(Event(run, EventKind.RUN_END, -1, "render server stopping",
                          {"chunks": 7, "steps_rendered": 3, "steps_skipped": 1, "timed_out": 1,
                           "evicted": 0, "late": 0, "duplicates": 0, "inbox_dropped": 0,
                           "queued_at_stop": 0, "lost_in_transit": 0, "ranks_lost": [1],
                           "rejected": 0, "view_errors": 1, "frames": 6}))
    return path


@pytest.fixture
def log_path(tmp_path):
    return write_log(tmp_path / "run.mcap")


def test_timing_table_means_and_shares(log_path):
    log = load_run(log_path)
    assert log.run == RUN and log.frames == {"side": 3, "top": 2}
    t = timing_table(log)
    assert [s.step for s in t.steps] == [20, 40, 60]
    assert [s.render_s for s in t.steps] == pytest.approx([0.008, 0.016, 0.024])
    assert [s.total_s for s in t.steps] == pytest.approx([0.020, 0.040, 0.060])
    p = t.per_step
    assert p.count == 3
    assert (p.receive_s, p.setup_s, p.render_s, p.total_s) == pytest.approx(
        (0.020, 0.004, 0.016, 0.040))
    assert [p.share(k) for k in ("receive", "setup", "render")] == pytest.approx([0.5, 0.1, 0.4])
    side, top = t.per_view["side"], t.per_view["top"]
    assert (side.count, top.count) == (3, 3)
    assert (side.render_s, top.render_s) == pytest.approx((0.006, 0.010))
    assert (side.total_s, top.total_s) == pytest.approx((0.030, 0.034))
    assert top.share("render") == pytest.approx(0.010 / 0.034)


def test_bytes_against_a_full_dump(log_path):
    log = load_run(log_path)
    b = byte_summary(log)
    assert b.received == {20: 2_000_000, 40: 1_000_000, 60: 2_000_000}
    assert b.received_total == 5_000_000 and b.particles_received == 250
    assert b.total_particles == PARTICLES and "run_start" in b.particles_source
    assert b.full_dump == {s: PARTICLES * PARTICLE_BYTES for s in (20, 40, 60)}
    assert b.full_dump_total == 48_000_000
    assert b.chunks_logged == 7
    assert b.chunk_bytes_logged == sum(len(chunk(s, r).encode())
                                       for s, rs in CHUNK_STEPS.items() for r in rs)


def test_skipped_and_incomplete_steps(log_path):
    acc = step_accounting(load_run(log_path))
    assert acc.rendered == [20, 40, 60]
    assert [(s.step, s.ranks_received, s.ranks_expected) for s in acc.incomplete] == [(40, 1, 2)]
    assert acc.unrendered == [80]
    assert acc.short == [(40, 1, 2)]
    assert acc.server["steps_skipped"] == 1 and acc.server["timed_out"] == 1
    assert sorted(acc.ranks_done) == [0, 1]
    assert acc.errors == ["view 'x' needs field 'y'"]


def test_markdown_holds_the_numbers(log_path):
    text = markdown(load_run(log_path))
    for line in ["| receive | 20.000 | 50.0 % |", "| setup | 4.000 | 10.0 % |",
                 "| render | 16.000 | 40.0 % |", "| total | 40.000 | 100.0 % |",
                 "| side | 3 | 3 | 20.000 | 4.000 | 6.000 | 30.000 | 66.7 % | 13.3 % | 20.0 % |",
                 "| top | 2 | 3 | 20.000 | 4.000 | 10.000 | 34.000 | 58.8 % | 11.8 % | 29.4 % |",
                 "- particles in the run: 1000000 (run_start event of sim rank 0)",
                 "received at the 3 rendered steps: 5.000 MB",
                 "48.000 MB; received / full dump = 10.4 %",
                 "- particles received: 250 of 3000000 (1000000 x 3 steps) = 0.0 %",
                 "- incomplete rendered steps: 1; step 40: 1 of 2 ranks",
                 "- steps with chunks in the log but not rendered: 1 (80)",
                 "steps_skipped 1, timed_out 1",
                 "inbox_dropped 0, queued_at_stop 0, lost_in_transit 0, ranks_lost [1]",
                 "chunks scheduled 8, sent 7, dropped 1", "- error events: 1",
                 "| 40 | 0.0040 | 2 | 20.000 | 4.000 | 16.000 | 40.000 | 50 | 1/2 incomplete "
                 "| 1.000 | 16.000 |"]:
        assert line in text, line


def test_particle_total_from_rank_done_or_unculled_chunks(tmp_path):
    log = load_run(write_log(tmp_path / "a.mcap", spec=True, events=False))
    n, source = total_particles(log)  # the spec culls nothing: a complete step's chunks
    assert n == 2 * PER_CHUNK and "chunk counts of step 20" in source
    spec = log.spec
    for change in ({"decimate": 2}, {"occlusion_cull": True}):  # chunks hold only some
        log.spec = dataclasses.replace(spec, views=tuple(
            dataclasses.replace(v, **change) for v in spec.views))
        assert total_particles(log)[0] is None
    log.spec = spec
    log.events.append(Event(RUN, EventKind.RANK_DONE, 0, "", {"particles": 7}))
    log.events.append(Event(RUN, EventKind.RANK_DONE, 1, "", {"particles": 5}))
    assert total_particles(log) == (12, "sum of the rank_done events of 2 rank(s)")


def test_unknown_particle_total_is_said(tmp_path):
    log = load_run(write_log(tmp_path / "b.mcap", events=False))  # no spec, no events
    b = byte_summary(log)
    assert b.total_particles is None and b.full_dump is None
    text = markdown(log)
    assert "- particles in the run: unknown:" in text
    assert "- full dump: unknown (the particle total is not in the log)" in text
    assert "server run_end summary: none in the log" in text


def test_plots_are_pngs(log_path, tmp_path):
    paths = plots(load_run(log_path), tmp_path / "plots")
    assert [p.name for p in paths] == ["run.timing.png", "run.bytes.png"]
    for p in paths:
        assert p.read_bytes()[:8] == PNG_SIGNATURE and p.stat().st_size > 1000


def test_cli_report_writes_markdown_and_plots(log_path, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "minority", "report", str(log_path),
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "| receive | 20.000 | 50.0 % |" in proc.stdout
    assert "received / full dump = 10.4 %" in proc.stdout
    for name in ("run.timing.png", "run.bytes.png"):
        assert (out / name).read_bytes()[:8] == PNG_SIGNATURE
        assert f"{out / name}" in proc.stdout
    from PIL import Image

    with Image.open(out / "run.timing.png") as image:
        image.verify()


def test_cli_plots_beside_the_log_or_none(log_path, capsys):
    assert main(["report", str(log_path), "--no-plots"]) == 0
    assert "| total | 40.000 | 100.0 % |" in capsys.readouterr().out
    assert not list(log_path.parent.glob("*.png"))
    assert main(["report", str(log_path)]) == 0
    assert sorted(p.name for p in log_path.parent.glob("*.png")) == ["run.bytes.png",
                                                                      "run.timing.png"]


def _bad(tmp_path):
    (tmp_path / "text.mcap").write_text("not an mcap file\n")
    write_log(tmp_path / "events.mcap", timings=False)
    with LogWriter(tmp_path / "two.mcap") as w:
        for run in ("r1", "r2"):
            w.write(Timing(run, 20, "side", 0.002, 0.01, 0.002, 0.03, 10, 1, 1, 1, False))
    return {"missing.mcap": "no such file", "text.mcap": "not an MCAP file",
            "events.mcap": "no timing records", "two.mcap": "several runs (r1, r2)"}


def test_bad_input_fails_in_one_line(tmp_path, capsys):
    for name, reason in _bad(tmp_path).items():
        with pytest.raises(RunLogError, match=reason.replace("(", r"\(").replace(")", r"\)")):
            load_run(tmp_path / name)
        assert main(["report", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("minority report: error: ") and reason in err
        assert err.count("\n") == 1
    assert main(["report", str(tmp_path / "two.mcap"), "--run", "r2", "--no-plots"]) == 0
    assert "run `r2`" in capsys.readouterr().out
    assert main(["report", str(tmp_path / "two.mcap"), "--run", "r3"]) == 2
    with pytest.raises(SystemExit) as usage:  # one log at a time: argparse's usage, status 2
        main(["report", str(tmp_path / "two.mcap"), "extra.mcap"])
    assert usage.value.code == 2
    assert "usage: minority report" in capsys.readouterr().err


def test_cli_bad_input_has_no_traceback(tmp_path):
    _bad(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "minority", "report", str(tmp_path / "text.mcap")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().endswith("not an MCAP file (no MCAP magic at its start)")


def test_an_indexed_log_and_the_same_log_cut_short_report_the_same(log_path, tmp_path,
                                                                     monkeypatch):
    """A complete log is read through its index (frames and rejected records counted from
    its summary, never read); the same log without its footer is read front to back."""
    from minority.protocol import runlog

    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log_path.read_bytes()[:-20])
    asked = []
    real = runlog.read_log_noting

    def spy(path, notes, topics=None):
        asked.append(topics)
        return real(path, notes, topics)

    monkeypatch.setattr(runlog, "read_log_noting", spy)
    whole, said = load_run(log_path), []
    short = load_run(cut, notice=said.append)
    assert asked[0] is not None and not any("frame" in t for t in asked[0])
    assert asked[1] is None  # no summary: everything, once
    fields = ("run", "runs", "timings", "events", "chunks", "frames", "spec", "rejected",
              "undecodable")
    assert [getattr(whole, f) for f in fields] == [getattr(short, f) for f in fields]
    assert whole.frames == {"side": 3, "top": 2} and not whole.notes
    assert [n.kind for n in short.notes] == ["truncated"] and len(said) == 1
    assert markdown(whole).replace(str(log_path), "L") == markdown(
        dataclasses.replace(short, notes=())).replace(str(cut), "L")

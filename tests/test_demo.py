"""The demo end to end at reduced size (1,800 particles, 0.3 s, small frames): oracle,
server process, 2 MPI ranks, frames, log, report and score; its log replays pixel-identical
with its own spec."""

import contextlib
import io
import json

import numpy as np
import pytest
from PIL import Image

from minority.demo import RUN, DemoOptions, main
from minority.replay import replay


@pytest.fixture(scope="module")
def small_demo(tmp_path_factory):
    """The demo's out folder and what it printed (stdout and its progress lines)."""
    out = tmp_path_factory.mktemp("small") / "demo"
    o = DemoOptions(out=out, ranks=2, duration_s=0.3, cell_size_m=0.032, frames=12, width=160,
                    height=120, timeout_s=300, http="127.0.0.1:0")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        assert main(o) == 0
    return out, printed.getvalue()


def test_small_demo_runs_end_to_end_and_replays_identically(small_demo, tmp_path):
    out, printed = small_demo
    assert "Oracle score" in printed and "run.mcap" in printed
    for name in ("spec.json", "run.mcap", "sim.h5", "report.md", "score.json",
                 "oracle/rollout.h5", "oracle/preview.png", "oracle/vtk/rollout.pvd",
                 "oracle/cameras/side.pvcc"):
        assert (out / name).is_file(), name
    frames = sorted((out / "frames" / RUN).glob("*/*.png"))
    assert {p.parent.name for p in frames} == {"side", "top", "aerial"}
    score = json.loads((out / "score.json").read_text())
    assert score["particles"] == 1800 and score["frames"]["oracle"] == len(frames)
    assert score["stats_steps"] >= 55  # every 5 ms over 0.3 s, per step all ranks
    report = (out / "report.md").read_text()
    assert "| receive |" in report and "particles in the run: 1800" in report
    summary = replay(out / "run.mcap", out=tmp_path / "again")
    assert summary is not None
    for png in frames:
        again = tmp_path / "again" / png.parent.name / png.name
        np.testing.assert_array_equal(np.asarray(Image.open(again)), np.asarray(Image.open(png)))
    from test_schemas import validate_log

    counts = validate_log(out / "run.mcap")  # every JSON message against its stored schema
    assert counts["minority.Spec"] >= 1 and counts["foxglove.CompressedImage"] == len(frames)


def test_small_demo_draws_the_outside_from_the_cache_and_serves_a_live_view(small_demo):
    """The ranks sent the particles outside the regions once and the server drew them from
    its cache (the Timing says so); the server's live view was on at the address printed."""
    import re

    from minority.protocol import Timing
    from minority.protocol.log import read_log

    out, printed = small_demo
    timings = [r.decode() for r in read_log(out / "run.mcap", topics=["minority/*/timing"])]
    assert timings and all(isinstance(t, Timing) for t in timings)
    assert any(t.cached > 0 for t in timings)
    assert all(t.cached <= t.particles for t in timings)
    url = re.search(r"live view: (http://127\.0\.0\.1:\d+/)", printed)
    assert url, printed
    assert f"live view: {url.group(1)}" in (out / "server.log").read_text()


def test_small_demo_writes_a_movie_and_an_animation_per_view(small_demo):
    import imageio_ffmpeg

    out, printed = small_demo
    assert "VIEW.mp4" in printed and "VIEW.webp" in printed
    for name in ("side", "top", "aerial"):
        pngs = list((out / "frames" / RUN / name).glob("*.png"))
        reader = imageio_ffmpeg.read_frames(str(out / "frames" / RUN / f"{name}.mp4"))
        meta = next(reader)
        assert meta["codec"] == "h264" and meta["size"] == (160, 120)
        assert sum(1 for _ in reader) == len(pngs)  # one movie frame per frame
        webp = out / "frames" / RUN / f"{name}.webp"
        assert webp.stat().st_size < 1_000_000
        with Image.open(webp) as im:
            assert im.is_animated and im.size == (160, 120)  # under 320 px: not scaled


def test_small_demo_runs_the_closed_loop_oracle_beside_the_server(small_demo):
    """The follower started before the sim and ended with the run; each spec update it put
    is a JSON line of its log and a spec of the run's log with the same provenance."""
    from minority.protocol.runlog import log_specs

    out, printed = small_demo
    assert "follow.log" in printed and "closed-loop oracle: pid" in printed
    lines = (out / "follow.log").read_text().splitlines()
    assert lines[0] == f"oracle follow: following run {RUN!r}"
    assert lines[-1].startswith("oracle follow: ") and "updates" in lines[-1]
    updates = [json.loads(line) for line in lines if line.startswith("{")]
    assert all(u["kind"] in ("shift", "forecast", "end") and u["reason"] for u in updates)
    logged = [s.provenance for s in log_specs(out / "run.mcap") if "update" in s.provenance]
    put = [(u["update"], u["kind"]) for u in updates]
    # the server logs each update it took (one put as the run ended may come too late)
    assert [(p["update"], p["kind"]) for p in logged] == put[:len(logged)]
    assert len(logged) >= len(put) - 1

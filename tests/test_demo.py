"""The demo end to end at reduced size (1,800 particles, 0.3 s, small frames): oracle,
server process, 2 MPI ranks, frames, log, report and score; its log replays pixel-identical
with its own spec."""

import json

import numpy as np
from PIL import Image

from minority.demo import RUN, DemoOptions, main
from minority.replay import replay


def test_small_demo_runs_end_to_end_and_replays_identically(tmp_path, capsys):
    out = tmp_path / "demo"
    o = DemoOptions(out=out, ranks=2, duration_s=0.3, cell_size_m=0.032, frames=12, width=160,
                    height=120, timeout_s=300)
    assert main(o) == 0
    printed = capsys.readouterr().out
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

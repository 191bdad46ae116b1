"""`minority replay`: a log recorded by the render daemon re-renders pixel-identical with its
own spec; a new spec's views that need data the log lacks are reported, not rendered; the
steps export to a VTK series ParaView reads; re-publishing to a second server renders the
same frames. Loopback only, multicast scouting off; waits are on counts."""

import io
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from conftest import free_port, make_chunk
from PIL import Image
from test_loopback import wait_until
from test_render_daemon import EveryStep

from minority.cli import main
from minority.protocol import Frame, ProtocolError, Spec, keys
from minority.protocol.log import read_log
from minority.protocol.republish import REPLAY_QOS
from minority.protocol.runlog import log_run, log_specs
from minority.protocol.session import LOSSLESS_QOS, NetworkOptions, Role, open_session, put
from minority.protocol.spec import Region, View
from minority.render_server.assemble import AssembledStep
from minority.render_server.daemon import RenderServer, ServerOptions
from minority.render_server.rerender import UNRECORDED, covered, missing_data, unrecorded
from minority.replay import replay

RUN = "replay-run"
STEPS = (0, 20, 40, 50)  # 50 is not scheduled: recorded, not rendered
RENDERED = (0, 20, 40)
REGIONS = [{"name": "left", "lo_m": [0.0, 0.0, 0.0], "hi_m": [0.6, 1.0, 1.0]},
           {"name": "inner", "lo_m": [0.1, 0.1, 0.1], "hi_m": [0.5, 0.9, 0.9]},
           {"name": "right", "lo_m": [0.7, 0.0, 0.0], "hi_m": [1.0, 1.0, 1.0]}]
SIDE = {"position": [0.5, -2.0, 0.5], "focal_point": [0.5, 0.5, 0.5]}
TOP = {"position": [0.5, 0.5, 3.0], "focal_point": [0.5, 0.5, 0.0], "view_up": [0, 1, 0]}
GRAY = {"Name": "my gray", "ColorSpace": "RGB", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]}


def view(name, camera=SIDE, **kw) -> dict:
    return {"name": name, "camera": camera, "width": 48, "height": 36, **kw}


def make_spec(*views) -> Spec:
    return Spec.from_dict({"version": 2, "run": RUN, "views": list(views), "regions": REGIONS})


RECORDED = make_spec(
    view("side", field="displacement", colormap="Cool to Warm",
         schedule=[{"every_steps": 20, "regions": ["left"]}]),
    view("top", TOP, field="velocity_magnitude", colormap=GRAY, decimate=2,
         schedule=[{"every_steps": 20, "regions": ["left"]}]))


def chunk(step, rank, ranks=2, n=60):
    c = make_chunk(n=n, step=step, rank=rank, ranks=ranks, seed=step * 10 + rank, run=RUN)
    c.fields["id"] = np.arange(rank * n, (rank + 1) * n, dtype=np.int64)
    c.prev_time_s = (step - 1) * 1e-4 if step else None
    return c


def pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A log written by the render daemon: the spec, 4 steps of 2 ranks, 6 frames."""
    tmp = tmp_path_factory.mktemp("recorded")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    sim = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5.0), Role.CLIENT)
    daemon = RenderServer(server, ServerOptions(RECORDED, tmp / "frames", tmp / "run.mcap",
                                                timeout_s=30.0))
    daemon._latest = EveryStep()
    try:
        for step in STEPS:
            for rank in range(2):
                put(sim, keys.chunk(RUN, step, rank), chunk(step, rank).encode(), LOSSLESS_QOS)
        assert wait_until(lambda: daemon.stats.chunks == 8 and daemon.stats.frames == 6)
    finally:
        daemon.close()
        sim.close()
        server.close()
    return tmp


def logged_frames(log) -> dict:
    frames = [r.decode() for r in read_log(log, [f"minority/{RUN}/frame/*"])]
    return {(f.view, f.step): pixels(f.png) for f in frames if isinstance(f, Frame)}


def test_own_spec_replays_pixel_identical(recorded, tmp_path, capsys):
    log = recorded / "run.mcap"
    assert log_specs(log)[-1] == RECORDED
    expected = logged_frames(log)
    assert sorted(expected) == sorted((v, s) for v in ("side", "top") for s in RENDERED)
    assert main(["replay", str(log), "--out", str(tmp_path / "out"), "-q"]) == 0
    out = capsys.readouterr().out
    assert "4 steps replayed with the log's spec, 6 frames" in out
    assert "NOT RENDERED" not in out and "incomplete" not in out
    for (name, step), image in expected.items():
        png = (tmp_path / "out" / name / f"{step:06d}.png").read_bytes()
        np.testing.assert_array_equal(pixels(png), image)


def test_views_needing_data_the_log_lacks_are_reported(recorded, tmp_path):
    new = make_spec(view("pressure", field="pressure", schedule=[{"regions": ["inner"]}]),
                    view("right", field="displacement", schedule=[{"regions": ["right"]}]),
                    view("everything", field="displacement"),
                    view("inner", field="displacement", decimate=3,
                         schedule=[{"every_steps": 10, "regions": ["inner"]}]))
    s = replay(recorded / "run.mcap", new, tmp_path / "out")
    problems = {name: dict(v.problems) for name, v in s.views.items()}
    assert s.views["pressure"].frames == 0 and not (tmp_path / "out" / "pressure").exists()
    (why, steps), = problems["pressure"].items()
    assert "field 'pressure' is not in the log" in why and steps == list(RENDERED)
    (why, _), = problems["right"].items()
    assert "regions right" in why and "only the particles in regions left" in why
    (why, _), = problems["everything"].items()
    assert why.startswith("it shows every particle")
    assert s.views["inner"].frames == 4  # 0, 20, 40 inside "left"; 50 was never culled
    assert problems["inner"] == {UNRECORDED: [10, 30]}
    assert s.unchecked == 1  # step 50: the recorded spec did not ask for it
    assert sorted(p.name for p in (tmp_path / "out" / "inner").iterdir()) == \
        [f"{k:06d}.png" for k in STEPS]
    assert "NOT RENDERED at 3 steps (0, 20, 40): field 'pressure'" in s.text()


def test_vtk_series_round_trip(recorded, tmp_path):
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    assert main(["replay", str(recorded / "run.mcap"), "--vtk", str(tmp_path / "vtk"), "-q"]) == 0
    assert not (recorded / "run-replay").exists()  # --vtk alone renders nothing
    datasets = ET.parse(tmp_path / "vtk" / f"{RUN}.pvd").getroot().find("Collection")
    entries = [(float(d.get("timestep")), d.get("file")) for d in datasets]
    assert entries == [(s * 1e-4, f"{RUN}_{s:06d}.vtp") for s in STEPS]
    for step, (_, name) in zip(STEPS, entries, strict=True):
        reader = vtkXMLPolyDataReader()
        reader.SetFileName(str(tmp_path / "vtk" / name))
        reader.Update()
        poly = reader.GetOutput()
        chunks = [chunk(step, r) for r in range(2)]
        assert poly.GetNumberOfVerts() == 120
        np.testing.assert_array_equal(vtk_to_numpy(poly.GetPoints().GetData()),
                                      np.concatenate([c.positions for c in chunks]))
        data = poly.GetPointData()
        for field in ("displacement", "velocity_magnitude", "material", "id"):
            np.testing.assert_array_equal(vtk_to_numpy(data.GetArray(field)),
                                          np.concatenate([c.fields[field] for c in chunks]))
        assert vtk_to_numpy(poly.GetFieldData().GetArray("TimeValue"))[0] == step * 1e-4


def test_publish_to_a_second_server_renders_the_same_frames(recorded, server, endpoint,
                                                            tmp_path, capsys):
    from minority.insitu.publisher import SENDER_QOS

    assert REPLAY_QOS == SENDER_QOS  # the simulation's QoS
    daemon = RenderServer(server, ServerOptions(RECORDED, tmp_path / "frames", None,
                                                timeout_s=30.0))
    daemon._latest = EveryStep()
    try:
        assert main(["replay", str(recorded / "run.mcap"), "--publish", "--rate", "100",
                     "--connect", endpoint, "-q"]) == 0
        assert "re-published 8 chunks and 1 specs" in capsys.readouterr().out
        assert wait_until(lambda: daemon.stats.frames == 6)
    finally:
        daemon.close()
    for name in ("side", "top"):
        for step in RENDERED:
            again = (tmp_path / "frames" / RUN / name / f"{step:06d}.png").read_bytes()
            first = (recorded / "frames" / RUN / name / f"{step:06d}.png").read_bytes()
            np.testing.assert_array_equal(pixels(again), pixels(first))


def test_publish_without_a_server_fails_clearly(recorded, server, endpoint, capsys):
    assert main(["replay", str(recorded / "run.mcap"), "--publish", "--rate", "0",
                 "--connect", endpoint, "--wait", "0.2", "-q"]) == 1
    assert "no render server subscribes" in capsys.readouterr().err


def test_bad_input_exits_2(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "none.mcap")]) == 2
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file")
    assert main(["replay", str(tmp_path / "junk.mcap"), "-q"]) == 2
    assert "junk.mcap: not an MCAP file" in capsys.readouterr().err
    with pytest.raises(ProtocolError, match="not an MCAP file"):
        replay(tmp_path / "junk.mcap", out=tmp_path / "out")
    (tmp_path / "empty.mcap").write_bytes(b"")  # a recorder killed at once: nothing in it
    assert main(["replay", str(tmp_path / "empty.mcap"), "-q"]) == 2
    assert "no chunks and no spec" in capsys.readouterr().err


def box(name, lo, hi) -> Region:
    return Region(name, tuple(map(float, lo)), tuple(map(float, hi)))


def test_regions_covered_by_a_union_of_boxes():
    a, b = box("a", (0, 0, 0), (1, 1, 1)), box("b", (1, 0, 0), (2, 1, 1))
    assert covered((box("x", (0.5, 0.2, 0.2), (1.5, 0.8, 0.8)),), (a, b))  # spans both
    assert not covered((box("x", (0.5, 0.2, 0.2), (2.5, 0.8, 0.8)),), (a, b))
    assert not covered((box("x", (0.5, 0.2, 0.2), (1.5, 0.8, 0.8)),),
                       (a, box("c", (1.1, 0, 0), (2, 1, 1))))  # a gap in between
    assert covered((box("flat", (0.5, 0.5, 1), (1.5, 0.5, 1)),), (a, b))  # degenerate box


@pytest.mark.parametrize(("decimate", "ids", "why"), [
    (2, False, ""), (4, True, ""), (3, True, "left out"), (4, False, "needs particle ids")])
def test_decimation_the_recorded_stride_allows(decimate, ids, why):
    cam = SIDE
    old = make_spec(view("a", cam, decimate=2), view("b", cam, decimate=4))  # stride 2
    new = make_spec(view("n", cam, decimate=decimate))
    fields = {"displacement": np.zeros((4, 3), np.float32)}
    if ids:
        fields["id"] = np.arange(4) * 2
    step = AssembledStep(20, 0.002, np.zeros((4, 3), np.float32), fields, 0.01, 1, 1, 0, 0.0,
                         False, 0.0019)
    assert old.request(20, 0.002).decimate == 2
    got = missing_data(new, new.views[0], step, old)
    assert (why in got) if why else got == ""


def test_unrecorded_instants_of_every_s_windows():
    v = View.from_dict(view("t", schedule=[{"every_s": 0.5}]), "v")
    steps = [(s, s * 0.125, (s - 1) * 0.125) for s in range(1, 13) if s != 8]
    assert unrecorded(v, steps) == ["t=1 s"]
    assert unrecorded(v, [(s, s * 0.125, (s - 1) * 0.125) for s in range(1, 13)]) == []


def test_occlusion_culled_logs_serve_only_the_views_that_were_culled_for():
    old = make_spec(view("a", SIDE, occlusion_cull=True), view("b", TOP, occlusion_cull=True))
    step = AssembledStep(20, 0.002, np.zeros((4, 3), np.float32),
                         {"displacement": np.zeros((4, 3), np.float32)}, 0.01, 1, 1, 0, 0.0,
                         False, 0.0019)
    assert old.request(20, 0.002).visible_in  # the sim sent what a or b could see
    same = make_spec(view("again", TOP))  # b's camera and size: every particle it sees came
    assert missing_data(same, same.views[0], step, old) == ""
    moved = make_spec(view("moved", {**TOP, "position": [0.5, 0.4, 3.0]}))
    assert "occlusion_cull" in missing_data(moved, moved.views[0], step, old)
    bigger = make_spec(view("bigger", TOP, width=96))
    assert "occlusion_cull" in missing_data(bigger, bigger.views[0], step, old)


def test_a_log_without_a_spec_names_its_run_from_its_chunks(tmp_path, capsys):
    """Regression: log_run took the run of a log holding no spec from its first chunk with
    keys.parse (a key parser), which returns None for the log topic `minority/{run}/chunk`:
    `replay --vtk` or `--publish` of a sim-only log crashed with an AttributeError, and a
    plain replay with a traceback instead of "pass --spec"."""
    from minority.protocol.log import LogWriter


    path = tmp_path / "sim-only.mcap"
    with LogWriter(path) as log:
        for step in (0, 20):
            for rank in range(2):
                log.write(chunk(step, rank))
    assert log_run(path, log_specs(path)) == RUN
    summary = replay(path, out=None)  # assembles, renders nothing
    assert summary.run == RUN and summary.steps == 2 and not summary.incomplete
    with pytest.raises(ValueError, match=f"no spec of run '{RUN}' is recorded; pass --spec"):
        replay(path, out=tmp_path / "frames")
    assert main(["replay", str(path), "-q"]) == 2
    assert "pass --spec" in capsys.readouterr().err


def test_replay_reads_the_same_steps_from_a_log_cut_short(recorded, tmp_path):
    """A complete log is read through its index, a cut one front to back: the steps agree."""
    whole = recorded / "run.mcap"
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-20])  # the footer gone: no summary, read front to back
    said = []
    a, b = replay(whole, out=None), replay(cut, out=None, notice=said.append)
    assert (a.run, a.steps, a.incomplete) == (b.run, b.steps, b.incomplete) and a.steps == 4
    assert not a.log_notes and [n.kind for n in b.log_notes] == ["truncated"] and len(said) == 1

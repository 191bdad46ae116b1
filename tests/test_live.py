"""The live view (`minority serve --http`): the HTTP/SSE server on loopback without a browser
(page, stream, index, files, refusals), the observer never blocked by a browser that does
not read (counted drops), the command's flag, and a real headless Chromium watching a small
sim's run on a real render server. Waits are bounded and on events or counts, never sleeps."""

import http.client
import io
import json
import shutil
import signal
import socket
import subprocess
import sys
import threading

import numpy as np
import pytest
from conftest import free_port, make_png, make_spec
from test_loopback import TIMEOUT_S, wait_until
from test_render_daemon import EveryStep

from minority.cli import main
from minority.protocol import Event, EventKind, Frame, Spec, Stats, Timing
from minority.protocol.messages import SPEED_BINS
from minority.render_server.live import LiveView
from minority.render_server.live_http import parse_address

RUN = "test-run"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture
def live(tmp_path):
    view = LiveView(tmp_path / "out", "127.0.0.1", 0, push_interval_s=0.01)
    yield view
    view.close()


def get(live: LiveView, path: str, headers: dict | None = None):
    """(status, headers, body) of a GET sent as is (no client-side path normalization)."""
    conn = http.client.HTTPConnection(*live.httpd.server_address[:2], timeout=TIMEOUT_S)
    try:
        conn.request("GET", path, headers=headers or {})
        res = conn.getresponse()
        return res.status, dict(res.getheaders()), res.read()
    finally:
        conn.close()


class Stream:
    """An /events reader: parsed server-sent events, read with the socket's timeout."""

    def __init__(self, live: LiveView):
        self.conn = http.client.HTTPConnection(*live.httpd.server_address[:2], timeout=TIMEOUT_S)
        self.conn.request("GET", "/events")
        self.res = self.conn.getresponse()
        assert self.res.status == 200
        assert self.res.getheader("Content-Type") == "text/event-stream"

    def next(self, kind: str) -> dict:
        """The data of the next event of `kind` (others skipped)."""
        event = None
        while True:
            line = self.res.fp.readline()
            assert line, "the stream ended"
            line = line.decode().rstrip("\n")
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: ") and event == kind:
                return json.loads(line[6:])

    def close(self) -> None:
        self.conn.close()


def stats(rank: int, step: int, count: int, speed_sq: float, disp: float, hist) -> Stats:
    return Stats(RUN, rank, step, step * 1e-3, count, speed_sq, 1.0, disp, True,
                 list(hist), [0] * SPEED_BINS)


def histogram(bins: dict[int, int]) -> list[int]:
    h = [0] * SPEED_BINS
    for i, n in bins.items():
        h[i] = n
    return h


# --- without a browser ---------------------------------------------------------------------

def test_parse_address_defaults_to_loopback_and_names_bad_input():
    assert parse_address("8080") == ("127.0.0.1", 8080)
    assert parse_address("0.0.0.0:0") == ("0.0.0.0", 0)
    assert parse_address("[::1]:9000") == ("::1", 9000)
    assert parse_address("localhost:1") == ("localhost", 1)
    for bad, why in [("http", "port must be a number"), ("127.0.0.1:70000", "port must be"),
                     (":80", "no host"), ("::1:80", "IPv6 address in brackets"),
                     ("host:-1", "port must be")]:
        with pytest.raises(ValueError, match=why):
            parse_address(bad)


def test_the_page_loads_and_the_stream_pushes_a_frame_after_an_observer_call(live):
    status, headers, body = get(live, "/")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b"new EventSource(\"/events\")" in body and b"<svg id=\"timeline\"" in body
    assert b"http://" not in body.replace(b"http://www.w3.org/2000/svg", b"")  # nothing remote
    stream = Stream(live)
    try:
        assert stream.next("state")["runs"] == []
        live.observe(RUN, "minority/test-run/spec", make_spec())
        run = stream.next("run")
        assert run["name"] == RUN and [v["name"] for v in run["views"]] == ["side", "top"]
        png = make_png(5, 4)
        live.observe(RUN, "minority/test-run/frame/side", Frame(RUN, "side", 40, 0.004, 5, 4, png))
        frame = stream.next("frame")
        assert (frame["run"], frame["view"], frame["step"]) == (RUN, "side", 40)
        status, headers, body = get(live, frame["url"])
        assert status == 200 and headers["Content-Type"] == "image/png" and body == png
        assert get(live, f"/live/{RUN}/top.png")[0] == 404  # no frame of that view yet
        live.observe(RUN, "minority/test-run/event",
                     Event(RUN, EventKind.RANK_DONE, 1, "rank 1 done", {"sent": 3}))
        event = stream.next("event")
        assert (event["event"], event["rank"], event["detail"]) == ("rank_done", 1, {"sent": 3})
    finally:
        stream.close()


def test_the_timeline_sums_the_ranks_per_step_and_marks_what_moves(live):
    """Kinetic energy 1/2 sum |v|^2 and particles summed over ranks, max displacement the
    largest, moving = faster than 5 % of the peak 95 % speed (minority.score's reading of the
    histograms); a rank's stats count once per step; timing summed over the views."""
    from minority.protocol.flow import histogram_quantile, moving_count

    spec = Spec.from_dict({**make_spec().to_dict(),
                           "events": [{"name": "peak_motion", "time_s": 0.05,
                                       "tolerance_s": 0.01}]})
    live.observe(RUN, "spec", spec)
    fast, slow, rest = histogram({45: 30, 20: 10}), histogram({35: 25}), histogram({0: 40})
    for message in (stats(0, 10, 40, 8.0, 0.01, rest), stats(1, 10, 25, 2.0, 0.02, slow),
                    stats(0, 20, 40, 30.0, 0.05, fast), stats(1, 20, 25, 4.0, 0.03, slow),
                    stats(1, 20, 25, 4.0, 0.03, slow)):  # the same rank twice: once
        live.observe(RUN, "stats", message)
    for view, setup, render in (("side", 0.1, 0.2), ("top", 0.3, 0.4)):
        live.observe(RUN, "timing", Timing(RUN, 20, view, 0.02, 0.05, setup, render))
    tl = live.timeline(RUN)
    s = tl["stats"]
    assert s["step"] == [10, 20] and s["particles"] == [65, 65]
    assert s["kinetic_j_per_kg"] == [5.0, 17.0] and s["max_displacement_m"] == [0.02, 0.05]
    summed = np.array([np.add(rest, slow), np.add(fast, slow)])
    threshold = 0.05 * histogram_quantile(summed, 0.95).max()
    assert s["moving_speed_m_s"] == pytest.approx(threshold)
    assert s["moving_share"] == pytest.approx(moving_count(summed, threshold) / 65, rel=1e-5)
    assert 0 < s["moving_share"][0] < s["moving_share"][1] <= 1
    t = tl["timing"]
    assert t["step"] == [20] and t["receive_s"] == [0.05]
    assert t["setup_s"] == pytest.approx([0.4]) and t["render_s"] == pytest.approx([0.6])
    run = live.state()["runs"][0]
    assert run["predicted"] == [{"name": "peak_motion", "time_s": 0.05, "tolerance_s": 0.01}]


def test_the_index_lists_run_directories_and_serves_their_files(live):
    out = live.out_dir
    (out / "column" / "side").mkdir(parents=True)
    for step in (0, 20):
        (out / "column" / "side" / f"{step:06d}.png").write_bytes(make_png())
    movie = bytes(range(256)) * 10
    (out / "column" / "side.mp4").write_bytes(movie)
    (out / "column" / "report.md").write_text("# timing\n")
    (out / "column.mcap").write_bytes(b"\x89MCAP0\r\n")
    (out / "score.md").write_text("# score\n")
    (out / "empty").mkdir()  # nothing of a run in it: not listed
    status, _, body = get(live, "/api/index")
    index = json.loads(body)
    assert status == 200 and [r["name"] for r in index["runs"]] == ["column"]
    run = index["runs"][0]
    side = run["views"][0]
    assert (side["name"], side["frames"]) == ("side", 2)
    assert side["newest"] == "/files/column/side/000020.png"
    assert side["movie"] == "/files/column/side.mp4"
    assert {f["name"]: f["url"] for f in run["files"]} == {
        "report.md": "/files/column/report.md", "side.mp4": "/files/column/side.mp4",
        "column.mcap": "/files/column.mcap"}
    assert index["files"] == [{"name": "score.md", "url": "/files/score.md"}]
    status, headers, body = get(live, side["newest"])
    assert status == 200 and headers["Content-Type"] == "image/png" and body == make_png()
    status, headers, body = get(live, "/files/column/report.md")
    assert body == b"# timing\n" and headers["Content-Type"].startswith("text/plain")
    status, headers, body = get(live, side["movie"], {"Range": "bytes=100-199"})
    assert status == 206 and body == movie[100:200]
    assert headers["Content-Range"] == f"bytes 100-199/{len(movie)}"
    assert get(live, side["movie"], {"Range": "bytes=99999-"})[0] == 416
    status, _, body = get(live, side["dir"])
    assert status == 200 and b'href="/files/column/side/000000.png"' in body


def test_paths_outside_the_output_directory_are_refused(live, tmp_path):
    out = live.out_dir
    (out / "run").mkdir(parents=True)
    (out / "run" / "ok.md").write_text("inside")
    (tmp_path / "secret.txt").write_text("outside")
    (out / "link").symlink_to(tmp_path)  # a symlink out of --out
    assert get(live, "/files/run/ok.md")[2] == b"inside"
    for path in ("/files/../secret.txt", "/files/%2e%2e/secret.txt", "/files/run/../../secret.txt",
                 "/files/run/%2E%2E/%2E%2E/secret.txt", "/files/link/secret.txt",
                 f"/files/{tmp_path}/secret.txt", f"/files/%2F{str(tmp_path)[1:]}/secret.txt",
                 "/files/..%5Csecret.txt", "/files/run/ok.md%00", "/../secret.txt",
                 "/live/../../secret.txt"):
        status, _, body = get(live, path)
        assert status in (403, 404), path
        assert b"outside" not in body, path


def test_a_page_from_another_host_name_is_refused_on_loopback(live):
    """DNS rebinding: a page of evil.example that resolves to 127.0.0.1 sends its own Host."""
    assert get(live, "/api/state", {"Host": "evil.example:80"})[0] == 403
    assert get(live, "/api/state", {"Host": "localhost:1"})[0] == 200


def frame(step: int) -> Frame:
    return Frame(RUN, "side", step, step * 1e-3, 4, 3, make_png())


def test_a_queue_that_is_never_read_keeps_the_newest_and_counts_the_drops(live):
    client = live.subscribe()
    calls = 10 * live.client_capacity
    for step in range(calls):
        live.observe(RUN, "frame", frame(step))
    assert len(client) == live.client_capacity  # bounded
    assert client.dropped == calls + 1 - live.client_capacity  # + the state queued first
    newest = client.get(0)
    for _ in range(live.client_capacity - 1):
        newest = client.get(0) or newest
    assert b'"step":%d' % (calls - 1) in newest  # the newest kept, the oldest dropped
    assert live.dropped == client.dropped
    live.unsubscribe(client)
    assert live.dropped == calls + 1 - live.client_capacity  # counted after it left


def test_a_browser_that_never_reads_does_not_block_the_observer(live):
    """A real connection that never reads: its socket buffers fill, its server thread blocks
    on the write, its queue drops; the observer's calls all return and a reading client
    still gets the newest frame. Bounded by a count of calls, not by time."""
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect(live.httpd.server_address[:2])
    stalled.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    reader = Stream(live)
    reader.next("state")
    assert wait_until(lambda: len(live._clients) == 2)
    me = stalled.getsockname()
    stalled_q = next(c for c in live._clients if c.connection.getpeername() == me)
    done = {"calls": 0}
    max_calls = 500_000  # ~100 MB of events: far more than any socket buffer holds

    def publish():
        for step in range(max_calls):
            live.observe(RUN, "frame", frame(step))
            done["calls"] += 1
            if step % 1000 == 999 and stalled_q.dropped > 0:
                return

    thread = threading.Thread(target=publish)
    try:
        thread.start()
        thread.join(TIMEOUT_S * 4)
        assert not thread.is_alive(), "an observer call blocked"
        calls = done["calls"]
        assert calls < max_calls  # it stopped because the stalled client dropped
        q = stalled_q
        assert q.dropped > 0 and len(q) <= live.client_capacity
        # every event accounted for (+ the state queued first; one may be in the write)
        assert calls <= q.written + len(q) + q.dropped <= calls + 1
        last = None
        while last is None or last["step"] < calls - 1:  # the reader catches up to the end
            last = reader.next("frame")
    finally:
        stalled.close()
        reader.close()


def test_closing_ends_the_streams(tmp_path):
    view = LiveView(tmp_path, "127.0.0.1", 0)
    stream = Stream(view)
    stream.next("state")
    view.close()
    assert stream.res.fp.read().strip() == b""  # the stream ends (no hang, no more data)
    stream.close()


# --- the command ---------------------------------------------------------------------------

def test_serve_refuses_a_bad_address_and_a_port_in_use(tmp_path, capsys):
    make_spec().save(tmp_path / "spec.json")
    base = ["serve", "--spec", str(tmp_path / "spec.json"), "--out", str(tmp_path / "out"),
            "--listen", f"tcp/127.0.0.1:{free_port()}"]
    assert main([*base, "--http", "127.0.0.1:http"]) == 2
    assert "--http '127.0.0.1:http': the port must be a number" in capsys.readouterr().err
    assert main([*base, "--http", "no-such-host.invalid:0"]) == 2
    assert "cannot resolve the host 'no-such-host.invalid'" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main([*base, "--http", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err
    assert f"--http 127.0.0.1:{port}: cannot listen there" in err and "in use" in err


def test_serve_prints_the_url_and_serves_the_page_until_stopped(tmp_path):
    make_spec().save(tmp_path / "spec.json")
    proc = subprocess.Popen([sys.executable, "-m", "minority", "serve", "--spec",
                             str(tmp_path / "spec.json"), "--out", str(tmp_path / "out"),
                             "--no-record", "--http", "0", "--listen",
                             f"tcp/127.0.0.1:{free_port()}"], stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in proc.stderr:  # bounded by the process: it prints or exits
            lines.append(line)
            if line.startswith("serving run"):
                break
        url = next(line.split()[-1] for line in lines if line.startswith("live view: "))
        assert url.startswith("http://127.0.0.1:") and url.endswith("/")
        host, port = url[7:-1].split(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=TIMEOUT_S)
        conn.request("GET", "/api/state")
        runs = json.loads(conn.getresponse().read())["runs"]
        conn.close()
        assert [(r["name"], len(r["views"])) for r in runs] == [(RUN, 2)]  # the spec, observed
        proc.send_signal(signal.SIGINT)  # a clean stop: the listener closes with the daemon
        _, err = proc.communicate(timeout=TIMEOUT_S)
        assert proc.returncode == 0, err
        assert "stopped: " in err
        with pytest.raises(OSError):
            socket.create_connection((host, int(port)), timeout=TIMEOUT_S).close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=TIMEOUT_S)


# --- a real browser on a real run ----------------------------------------------------------

BROWSER_SPEC = {
    "version": 2, "run": RUN,
    "views": [{"name": "side", "camera": {"position": [0.2, -0.6, 0.08],
                                          "focal_point": [0.2, 0.02, 0.06]},
               "width": 96, "height": 64, "field": "displacement", "range": [0.0, 0.03],
               "colormap": "Viridis (matplotlib)", "background": [0.0, 0.0, 0.0],
               "every_steps": 10}],
    "events": [{"name": "failure_onset", "time_s": 0.004, "tolerance_s": 0.001},
               {"name": "peak_motion", "time_s": 0.012, "tolerance_s": 0.002}]}


@pytest.mark.skipif(not shutil.which(CHROMIUM), reason=f"no browser at {CHROMIUM} (Debian's "
                    "chromium package; .ci/run installs it)")
def test_a_browser_watches_a_run_live(server, endpoint, tmp_path):
    from PIL import Image
    from playwright.sync_api import sync_playwright

    from minority.insitu.publisher import PublishOptions
    from minority.protocol.session import NetworkOptions
    from minority.render_server.daemon import RenderServer, ServerOptions
    from minority.sim.ranks import RankRunConfig, run_ranks
    from minority.sim.scene import builtin_scene_path

    spec = Spec.from_dict(BROWSER_SPEC)
    view = LiveView(tmp_path / "frames", "127.0.0.1", 0, push_interval_s=0.05)
    daemon = RenderServer(server, ServerOptions(spec, tmp_path / "frames", None, timeout_s=30.0,
                                                observer=view.observe))
    daemon._latest = EveryStep()  # every scheduled step rendered, however slow this machine
    cfg = RankRunConfig(scene_path=builtin_scene_path("tiny"), out=None, progress=False, run=RUN,
                        max_steps=200, publish=PublishOptions(
                            network=NetworkOptions(connect=[endpoint]), stats_every_s=0.001))
    sim = threading.Thread(target=run_ranks, args=(cfg,), kwargs={"stream": io.StringIO()})
    wait_ms = TIMEOUT_S * 1000
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1100, "height": 900})
            errors = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(view.url)
            page.wait_for_selector("#conn.live", timeout=wait_ms)
            page.wait_for_selector(f'#run option[value="{RUN}"]', state="attached",
                                   timeout=wait_ms)
            sim.start()
            img = 'img[data-view="side"]'
            # a second frame loads into the same element while the run goes on
            page.wait_for_function(f"document.querySelector('{img}')?.dataset.frames >= 2",
                                   timeout=wait_ms)
            sim.join(TIMEOUT_S * 4)
            assert not sim.is_alive()
            assert daemon.finished.wait(TIMEOUT_S)
            newest = view.state()["runs"][0]["frames"]["side"]
            page.wait_for_function(f"document.querySelector('{img}').dataset.step === "
                                   f"'{newest['step']}'", timeout=wait_ms)
            points = len(view.timeline(RUN)["stats"]["step"])
            assert points >= 5
            page.wait_for_function("document.querySelector('#timeline polyline.kinetic')"
                                   f"?.points.numberOfItems === {points}", timeout=wait_ms)
            for cls in ("moving", "displacement"):
                assert page.evaluate(f"document.querySelector('#timeline polyline.{cls}')"
                                     ".points.numberOfItems") == points
            timed = len(view.timeline(RUN)["timing"]["step"])
            page.wait_for_function("document.querySelector('#timing polyline.render')"
                                   f"?.points.numberOfItems === {timed}", timeout=wait_ms)
            assert page.locator("#timeline line.pred").count() == len(spec.events)
            assert page.locator("#events li").count() >= 3  # run start, rank done, run end
            page.wait_for_selector(f'#index tr[data-run="{RUN}"]', timeout=wait_ms)
            box = page.locator(img).bounding_box()
            shot = Image.open(io.BytesIO(page.screenshot(clip=box))).convert("RGB")
            assert not errors, errors
            browser.close()
    finally:
        if sim.is_alive():
            sim.join(TIMEOUT_S * 4)
        daemon.close()
        view.close()
    # the screenshot's image area shows the newest frame (shrunk back to its pixels)
    png = Image.open(io.BytesIO(view.newest_png(RUN, "side") or b"")).convert("RGB")
    shown = np.asarray(shot.resize(png.size, Image.BOX), np.float64)
    frame_rgb = np.asarray(png, np.float64)
    assert frame_rgb.std() > 10  # the frame is not blank: sand on the background
    assert np.abs(shown - frame_rgb).mean() < 12

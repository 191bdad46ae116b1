"""Render server benchmark: chunks from a separate process over loopback zenoh, one view
1024x768, medians over several steps.

Prints one JSON object per particle count:
{"bench": "render", "particles": N, "width": 1024, "height": 768, "shadows", "receive_s",
 "setup_s", "render_s", "total_s"}
receive_s: the sender's stamp to the arrival of the chunk that completes the step, setup_s:
k-d bricks (and grids when shadows are on), render_s: ray casting and shading (PNG encoding
excluded), as the server's Timing messages report them, medians after WARMUP_STEPS steps.
The reference paper's Galaxy totals were 0.224, 2.521 and 3.376 s per in situ step at 13k,
100k and 1M particles.

Then one line for the annotations (render_server.overlay) of the same view over the heap's
domain, on a 13k-particle frame:
{"bench": "overlay", "width", "height", "compose_s" (once per view), "apply_s" (median per
frame: context, colorbar, time text), "context_px", "legend_px"}; --overlay-only prints just
that line (no network).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from minority.protocol import Chunk, Spec, Timing, decode_as, keys
from minority.protocol.session import LOSSLESS_QOS, Inbox, NetworkOptions, Role, open_session, put
from minority.render_server import overlay
from minority.render_server.daemon import RenderServer, ServerOptions
from minority.render_server.render import Canvas, prepare, render

RUN = "bench-render"
SIZES = {13_000: 20, 100_000: 15, 1_000_000: 12}  # particles -> steps
WARMUP_STEPS = 3  # dropped: shared-memory pool and page mapping warm up in a new sender
WIDTH, HEIGHT = 1024, 768
HEAP_M = (0.6, 0.144, 0.32)  # runout length, channel width, initial height of the heap, m
WAIT_S = 600.0
DOMAIN_M = ((0.0, 0.0, 0.0), (1.0, 0.144, 0.4))  # the chunks' bounds: floor z = 0, walls y
OVERLAY_FRAMES = 200  # frames the overlay is applied to (median)
KEYS = {"render": ("particles", "width", "height", "shadows", "receive_s", "setup_s", "render_s",
                   "total_s"),
        "overlay": ("width", "height", "compose_s", "apply_s", "context_px", "legend_px")}


def heap(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """A collapsed-column-like deposit: height H (1 - x/L)^2 over the channel. Returns
    positions [n, 3] float32 m, displacement [n, 3] float32 m and the particle spacing m."""
    rng = np.random.default_rng(seed)
    length, width, height = HEAP_M
    x = length * (1.0 - np.sqrt(rng.random(n)))  # denser near the back wall, like the profile
    z = height * (1.0 - x / length) ** 2 * rng.random(n)
    y = width * rng.random(n)
    volume = length * width * height / 3.0
    spacing = (volume / n) ** (1.0 / 3.0)
    pos = np.c_[x, y, z].astype(np.float32)
    disp = np.c_[x, np.zeros(n), z - height].astype(np.float32)
    return pos, disp, spacing


def spec() -> Spec:
    return Spec.from_dict({"version": 1, "run": RUN, "views": [{
        "name": "aerial", "camera": {"position": [0.9, -0.55, 0.55], "focal_point": [0.28, 0.07, 0.06],
                                     "view_up": [0, 0, 1], "view_angle_deg": 30},
        "width": WIDTH, "height": HEIGHT, "field": "displacement", "colormap": "Cool to Warm",
        "range": [0.0, 0.6], "every_steps": 1}]})


def sender(endpoint: str, n: int, first: int, steps: int) -> None:
    """Child process: one rank publishing a step after the previous one was rendered."""
    session = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=30), Role.CLIENT)
    timing = Inbox(session, keys.timing(RUN))
    pos, disp, spacing = heap(n)
    for step in range(first, first + steps):
        chunk = Chunk(RUN, step, step * 1e-4, 0, 1, spacing, DOMAIN_M,
                      {"positions": pos, "displacement": disp})
        put(session, keys.chunk(RUN, step, 0), chunk.encode(), LOSSLESS_QOS)
        if timing.get(timeout=WAIT_S) is None:
            raise SystemExit(f"bench render: no timing for step {step}")
    session.close()


def bench_overlay(n: int = 13_000) -> dict:
    """Compose the bench view's annotations once and apply them to a rendered frame again and
    again (its hit mask: the particles hide the floor's lines); seconds."""
    view = spec().views[0]
    pos, disp, spacing = heap(n)
    canvas = Canvas(view.width, view.height)
    image = render(prepare(pos, 0.5 * spacing, grids=False), disp, view, canvas=canvas).copy()
    t0 = time.perf_counter()
    made = overlay.OverlayCache().get(view, DOMAIN_M)
    compose_s = time.perf_counter() - t0
    times = []
    for k in range(OVERLAY_FRAMES):
        frame = image.copy()
        t0 = time.perf_counter()
        overlay.apply(made, frame, canvas.hit, k, k * 1e-4)
        times.append(time.perf_counter() - t0)
    return {"bench": "overlay", "width": view.width, "height": view.height,
            "compose_s": round(compose_s, 5), "apply_s": round(statistics.median(times), 6),
            "context_px": len(made.context.index), "legend_px": len(made.legend.index)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=17502, help="loopback TCP port")
    parser.add_argument("--sizes", type=int, nargs="*", default=list(SIZES))
    parser.add_argument("--shadows", action="store_true",
                        help="shadow rays on: setup_s then includes the per-brick grids")
    parser.add_argument("--overlay-only", action="store_true",
                        help="only the annotations' line: compose once, apply per frame")
    parser.add_argument("--sender", nargs=4, metavar=("ENDPOINT", "N", "FIRST", "STEPS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sender:
        sender(args.sender[0], *map(int, args.sender[1:]))
        return
    if args.overlay_only:
        print(json.dumps(bench_overlay()), flush=True)
        return
    endpoint = f"tcp/127.0.0.1:{args.port}"
    session = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    timing = Inbox(session, keys.timing(RUN), capacity=1024)
    with tempfile.TemporaryDirectory() as tmp:
        server = RenderServer(session, ServerOptions(spec(), Path(tmp), None, shadows=args.shadows,
                                                     write_png=False))
        first = 0  # steps keep increasing across sizes (the server drops older steps)
        for n in args.sizes:
            steps = SIZES.get(n, 5)
            child = subprocess.Popen([sys.executable, "-m", "bench.render", "--sender", endpoint,
                                      str(n), str(first), str(steps)])
            first += steps
            rows = []
            for _ in range(steps):
                item = timing.get(timeout=WAIT_S)
                if item is None:
                    raise SystemExit(f"bench render: timed out at {n} particles")
                rows.append(decode_as(item.payload, Timing))
            child.wait(timeout=WAIT_S)
            rows = rows[WARMUP_STEPS:]
            med = {k: statistics.median(getattr(r, k) for r in rows)
                   for k in ("receive_s", "setup_s", "render_s")}
            print(json.dumps({"bench": "render", "particles": n, "width": WIDTH, "height": HEIGHT,
                              "shadows": args.shadows, **{k: round(v, 5) for k, v in med.items()},
                              "total_s": round(sum(med.values()), 5)}), flush=True)
        server.close()
    session.close()
    print(json.dumps(bench_overlay()), flush=True)


if __name__ == "__main__":
    main()

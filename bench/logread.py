"""Log reading benchmark: one topic of a demo-size MCAP log read through its chunk index
(protocol.logread.read_log on a complete log) vs scanned front to back (use_index=False, as a
log without a summary is read).

The log is synthesized at the demo's size (`minority demo`: 12,960 particles on 2 ranks, 36
output steps of 0.02 s, 90 frames of 1024x768 in 3 views, Stats from every rank at every
step, one Timing per rendered view). `--flush steps` closes an MCAP chunk after every step,
as the recorder's 0.5 s flush does when a step takes longer than that; `--flush size` leaves
the 4 MiB chunk limit alone (every chunk then holds every topic).

Prints one JSON object per (flush, topic):
{"bench": "logread", "flush", "topic", "messages", "log_bytes", "chunks", "indexed_s",
 "scanned_s", "speedup"}  (medians over --repeat reads, page cache warm, seconds)
and one per (flush, reader) for what `minority report` (protocol.runlog.read_run) and
`minority report score` (read_flow) read, the log complete vs the same log without its
footer (read front to back, as the report read every log before the index):
{"bench": "logread", "flush", "reader", "log_bytes", "chunks", "indexed_s", "scanned_s",
 "speedup"}
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from PIL import Image

from minority.protocol import Chunk, Frame, Stats, Timing, keys
from minority.protocol.log import LogWriter, read_log
from minority.protocol.messages import speed_histogram
from minority.protocol.runlog import read_flow, read_run
from minority.protocol.spec import Spec

RUN = "bench"
PARTICLES = 12_960  # the demo's showcase column
RANKS = 2
STEPS = 36  # 0.7 s simulated, output every 0.02 s
VIEWS = ("side", "top", "oblique")
FRAME_STEPS = 30  # steps with a frame of every view: 90 frames
WIDTH, HEIGHT = 1024, 768  # px
DT_S = 0.02  # s of simulated time per output step
KEYS = {"logread": ("flush", "topic", "messages", "log_bytes", "chunks", "indexed_s",
                     "scanned_s", "speedup"),
        "logread reader": ("flush", "reader", "log_bytes", "chunks", "indexed_s", "scanned_s",
                           "speedup")}
TOPICS = {"timing": keys.log_topic(RUN, keys.Topic.TIMING),
          "frame/side": keys.log_topic(RUN, keys.Topic.FRAME, "side"),
          "stats": keys.log_topic(RUN, keys.Topic.STATS),
          "chunk": keys.log_topic(RUN, keys.Topic.CHUNK)}


def frame_png(seed: int) -> bytes:
    """A 1024x768 PNG of the size a rendered frame has (a smooth image with some noise)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    rgb = np.stack([x * 255 // WIDTH, y * 255 // HEIGHT, (x + y + seed) % 256], -1)
    rgb[rng.random((HEIGHT, WIDTH)) < 0.05] = 0
    buf = io.BytesIO()
    Image.fromarray(rgb.astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def write_demo_log(path: Path, flush_steps: bool) -> None:
    rng = np.random.default_rng(0)
    n = PARTICLES // RANKS
    cam = {"position": [0.4, -1.0, 0.2], "focal_point": [0.4, 0.07, 0.1]}
    spec = Spec.from_dict({"version": 2, "run": RUN, "views": [
        {"name": v, "camera": cam, "schedule": [{"every_steps": 1}]} for v in VIEWS]})
    pngs = [frame_png(k) for k in range(4)]
    ns = 1
    with LogWriter(path, flush_interval_s=1e9) as log:
        log.write(spec, log_ns=ns)
        for step in range(STEPS):
            t = step * DT_S
            for rank in range(RANKS):
                v = rng.random(n) * 2.0
                log.write(Stats(RUN, rank, step, t, n, float((v * v).sum()), float(v.max()),
                                0.1, True, speed_histogram(v), speed_histogram(v[:0])),
                          log_ns=(ns := ns + 1))
                log.write(Chunk(RUN, step, t, rank, RANKS, 0.016, ((0, 0, 0), (0.8, 0.4, 0.2)),
                                {"positions": rng.random((n, 3), dtype=np.float32),
                                 "velocity": rng.random((n, 3), dtype=np.float32),
                                 "displacement_magnitude": rng.random(n, dtype=np.float32)}),
                          log_ns=(ns := ns + 1))
            if step < FRAME_STEPS:
                for k, view in enumerate(VIEWS):
                    log.write(Frame(RUN, view, step, t, WIDTH, HEIGHT, pngs[(step + k) % 4]),
                              log_ns=(ns := ns + 1))
                    log.write(Timing(RUN, step, view, t, 0.01, 0.002, 0.03, 2_000_000,
                                     PARTICLES, RANKS, RANKS, False), log_ns=(ns := ns + 1))
            if flush_steps:
                log.flush()


def timed(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5, help="reads per measurement (median)")
    p.add_argument("--flush", choices=("steps", "size", "both"), default="both")
    p.add_argument("--dir", type=Path, help="where the log is written (default: a temp dir)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for flush in (("steps", "size") if args.flush == "both" else (args.flush,)):
            path = (args.dir or Path(tmp)) / f"demo-{flush}.mcap"
            path.unlink(missing_ok=True)
            write_demo_log(path, flush == "steps")
            with open(path, "rb") as f:
                chunks = len(make_reader(f).get_summary().chunk_indexes)
            for name, topic in TOPICS.items():
                count = sum(1 for _ in read_log(path, [topic]))
                indexed = timed(lambda p=path, t=topic: sum(1 for _ in read_log(p, [t])),
                                args.repeat)
                scanned = timed(lambda p=path, t=topic: sum(
                    1 for _ in read_log(p, [t], use_index=False)), args.repeat)
                print(json.dumps({"bench": "logread", "flush": flush, "topic": name,
                                  "messages": count, "log_bytes": path.stat().st_size,
                                  "chunks": chunks, "indexed_s": round(indexed, 5),
                                  "scanned_s": round(scanned, 5),
                                  "speedup": round(scanned / indexed, 2)}), flush=True)
            cut = path.with_name(f"{path.stem}-cut.mcap")  # no footer: read front to back
            cut.write_bytes(path.read_bytes()[:-20])
            for name, read in (("report", lambda p: read_run(p, RUN, [])),
                               ("score", lambda p: read_flow(p, RUN, []))):
                indexed = timed(lambda p=path, r=read: r(p), args.repeat)
                scanned = timed(lambda p=cut, r=read: r(p), args.repeat)
                print(json.dumps({"bench": "logread", "flush": flush, "reader": name,
                                  "log_bytes": path.stat().st_size, "chunks": chunks,
                                  "indexed_s": round(indexed, 5), "scanned_s": round(scanned, 5),
                                  "speedup": round(scanned / indexed, 2)}), flush=True)


if __name__ == "__main__":
    main()

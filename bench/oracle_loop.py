"""The closed-loop oracle against the open loop, where the open loop fails: the held-out
scenes the shipped GNS gets 10 % or more wrong (test_003, wide_10x of
gns/configs/column_sweep_cg2.toml) and columns outside the training range (test_003's column
with friction angles of 20 and 45 deg, and a column of aspect ratio 5), each run by the MPM
on 2 ranks with the render server.

Per scene: the open-loop spec (the GNS from the MPM's first frames, as `minority demo` makes
it), then two runs with the server: the open loop (that spec alone) and the closed loop (the
same spec and `minority oracle follow`). Each prints a JSON line:
{"bench": "oracle_loop", "scene", "loop": "open"|"closed", "events_within", "events",
 "events_within_in_force", "regions_share", "frames_vs_ideal", "frames_in_critical",
 "frames_ratio", "bytes_share", "updates", "forecasts", "forecast_wall_s", "run_wall_s",
 "frames", "event_errors", "event_error_max", "displacement_error"}
- events_within: events of the run's last spec within 10 % (minority report score), of
  `events`; events_within_in_force: the same with, for each event, the spec in force when
  it happened (what the server worked with then); event_errors: each event's time error
  of the last spec, relative to the actual time ((predicted - actual) / actual), and
  event_error_max the largest in size; displacement_error: the last spec's predicted
  maximum displacement against the run's, relative;
- regions_share: moving particles inside the regions (the ranks' Stats, under the spec in
  force at each step);
- frames_vs_ideal: frames inside the actual critical windows against a fixed cadence of
  as many frames (in expectation: frames x critical share of the run), over the ideal ratio
  1 / (critical share): the share of the rendered frames that fall inside the windows
  (frames_in_critical of frames); frames_ratio: minority report score's ratio, against the
  fixed cadence's actual count (coarse when few frames fall inside);
- bytes_share: chunk bytes against every particle at every rendered step (snapshots count);
- updates, forecasts: spec updates put by the follower, and of those re-forecasts;
  forecast_wall_s: each re-forecast's wall time; run_wall_s: the 2-rank MPM run's.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "gns" / "configs" / "column_sweep_cg2.toml"
CHECKPOINT = ROOT / "gns" / "checkpoints" / "column_l64_m5.pt"
RUN = "loop"
SCENES = ("test_003", "friction_20", "friction_45", "aspect_5", "wide_10x")
KEYS = {"oracle_loop": ("scene", "loop", "events_within", "events", "events_within_in_force",
                        "regions_share", "frames_vs_ideal?", "frames_in_critical",
                        "frames_ratio?", "bytes_share", "updates", "forecasts",
                        "forecast_wall_s", "run_wall_s", "frames", "event_errors",
                        "event_error_max?", "displacement_error?")}


def scene_plans(names: list[str], config: Path = CONFIG):
    """The sweep plans of the scenes: the config's test scenes, or test_003's column with
    another friction angle, or a column of aspect ratio 5 (H0 0.32 m over L0 0.064 m)."""
    from minority.gns.sweep import load_config, plan

    cfg = load_config(config)
    plans = {p.name: p for p in plan(cfg) if p.split == "test"}
    base = plans["test_003"]
    plans["friction_20"] = replace(base, name="friction_20", friction_angle_deg=20.0)
    plans["friction_45"] = replace(base, name="friction_45", friction_angle_deg=45.0)
    plans["aspect_5"] = replace(base, name="aspect_5", length_m=0.064, height_m=0.32)
    unknown = [n for n in names if n not in plans]
    if unknown:
        raise SystemExit(f"oracle_loop: unknown scenes {unknown} (known: {', '.join(SCENES)})")
    return cfg, [plans[n] for n in names]


def open_spec(scene: Path, out: Path, frames: int, threads: int) -> Path:
    """The open-loop spec of the scene (run id RUN), as the demo makes it."""
    import torch

    from minority.gns.oracle import Oracle, OracleOptions
    from minority.warmstart import predict_scene

    torch.set_num_threads(threads)
    p = predict_scene(CHECKPOINT, scene)
    oracle = Oracle(p.positions, p.frame_interval_s, p.bounds_m, p.spacing_m,
                    OracleOptions(run=RUN, frames=frames))
    spec = oracle.spec({"checkpoint": str(CHECKPOINT), "scene": str(scene),
                        "rollout_wall_s": p.wall_s})
    path = out / "spec.json"
    spec.save(path)
    return path


def run_once(scene: Path, spec: Path, out: Path, closed: bool, threads: int,
             timeout_s: float) -> tuple[Path, float]:
    """Server, (follower), 2-rank sim; returns the server's log and the sim's wall s."""
    from minority.demo import free_port, wait_for_line

    out.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads)}
    log = out / "run.mcap"
    for old in out.glob("run*.mcap"):  # the server never overwrites a log: start afresh
        old.unlink()
    me = [sys.executable, "-m", "minority"]
    procs = []
    with open(out / "server.log", "w") as server_log, open(out / "follow.log", "w") as flog:
        procs.append(subprocess.Popen(
            [*me, "serve", "--spec", str(spec), "--out", str(out / "frames"), "--record",
             str(log), "--listen", endpoint, "--exit-when-done"], stdout=server_log,
            stderr=subprocess.STDOUT, env=env))
        try:
            if closed:  # once the server serves the spec (a busy machine starts it slowly)
                wait_for_line(out / "server.log", "serving run", procs[0], "the server")
                procs.append(subprocess.Popen(
                    [*me, "oracle", "follow", RUN, "--scene", str(scene), "--ranks", "2",
                     "--connect", endpoint, "--threads", str(threads), "--timeout",
                     str(timeout_s), "--wait", "120"], stdout=flog, stderr=subprocess.STDOUT,
                    env=env))
                # the follower reads the run from its first Stats on
                wait_for_line(out / "follow.log", "following run", procs[-1], "the follower")
            t0 = time.perf_counter()
            sim = subprocess.run([*me, "sim", str(scene), "--ranks", "2", "--run", RUN,
                                  "--connect", endpoint, "--wait", "60", "--out",
                                  str(out / "sim.h5"), "--threads", str(threads), "--quiet"],
                                 env=env, timeout=timeout_s, stdout=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            if sim.returncode != 0:
                raise RuntimeError(f"the simulation failed (exit {sim.returncode})")
            for p in procs:
                p.wait(timeout=300)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
                    try:
                        p.wait(timeout=60)
                    except subprocess.TimeoutExpired:
                        p.kill()
                        p.wait()
    logs = sorted(out.glob("run*.mcap"), key=lambda f: f.stat().st_mtime)
    return (logs[-1] if logs else log), wall


def in_force_within(log: Path, result: dict) -> int:
    """Events within 10 % of the prediction of the spec in force when each happened: the
    last spec logged before the first Stats at or after the event's actual time."""
    from minority.protocol.log import read_log
    from minority.protocol.messages import Stats
    from minority.protocol.spec import Spec

    specs, stats_time = [], -1.0  # (the run's time when logged, spec)
    for rec in read_log(log, topics=[f"minority/{RUN}/spec", f"minority/{RUN}/stats"]):
        msg = rec.decode()
        if isinstance(msg, Stats):
            stats_time = max(stats_time, msg.time_s)
        elif isinstance(msg, Spec):
            specs.append((stats_time, msg))
    n = 0
    for row in result["events"]:
        spec = [s for t, s in specs if t < row["actual_s"]][-1:] or [specs[0][1]]
        ev = {e.name: e for e in spec[-1].events}.get(row["event"])
        n += ev is not None and abs(ev.time_s - row["actual_s"]) <= row["tolerance_s"]
    return n


def measure(scene_name: str, loop: str, log: Path, wall: float) -> dict:
    from minority.protocol.runlog import log_specs
    from minority.score import load_run, score

    specs = log_specs(log)
    run = load_run(log)
    result = score(specs[-1], run)
    frames = result["frames"]
    forecasts = [s.provenance for s in specs if s.provenance.get("kind") == "forecast"]
    return {"bench": "oracle_loop", "scene": scene_name, "loop": loop,
            "events_within": sum(e["within_tolerance"] for e in result["events"]),
            "events": len(result["events"]),
            "events_within_in_force": in_force_within(log, result),
            "regions_share": result["roi_moving_fraction"],
            "frames_vs_ideal": (frames["oracle_in_critical"] / frames["oracle"]
                                if frames["oracle"] else None),
            "frames_in_critical": frames["oracle_in_critical"],
            "frames_ratio": frames["ratio"],
            "bytes_share": result["bytes"]["fraction"],
            "updates": sum("update" in s.provenance for s in specs),
            "forecasts": len(forecasts),
            "forecast_wall_s": [round(p["forecast_s"], 2) for p in forecasts],
            "run_wall_s": round(wall, 1),
            "frames": frames["oracle"],
            **event_errors(result)}


def event_errors(result: dict) -> dict:
    """The last spec's errors, relative to the run's: each event time's, the largest in
    size, and the maximum displacement's (None where the run's is 0)."""
    rel = {e["event"]: e["relative_error"] for e in result["events"]
           if e["relative_error"] is not None}
    return {"event_errors": {k: round(v, 4) for k, v in rel.items()},
            "event_error_max": round(max(map(abs, rel.values())), 4) if rel else None,
            "displacement_error": result["displacement_max_m"]["relative_error"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.oracle_loop", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES,
                    help="scenes to run (default: all five; wide_10x takes the longest)")
    ap.add_argument("--loops", nargs="+", default=["open", "closed"],
                    choices=["open", "closed"], help="which loops to run")
    ap.add_argument("--frames", type=int, default=120, help="frame budget, all views")
    ap.add_argument("--out", type=Path, default=Path("data/oracle_loop"),
                    help="working directory (scenes, specs, runs)")
    ap.add_argument("--new-spec", action="store_true",
                    help="derive each open-loop spec again (after a change to gns/oracle.py) "
                         "instead of reusing OUT/SCENE/spec.json")
    ap.add_argument("--threads", type=int, default=1, help="threads per process")
    ap.add_argument("--timeout", type=float, default=1800.0, help="wall s per run at most")
    ap.add_argument("--config", type=Path, default=CONFIG,
                    help="the sweep config whose test scenes these are (default: "
                         "gns/configs/column_sweep_cg2.toml; the checkpoint's resolution)")
    args = ap.parse_args(argv)
    from minority.sweep import scene_toml

    cfg, plans = scene_plans(args.scenes, args.config)
    for p in plans:
        d = args.out / p.name
        d.mkdir(parents=True, exist_ok=True)
        scene = d / f"{p.name}.toml"
        scene.write_text(scene_toml(cfg, p))
        spec = d / "spec.json"
        if args.new_spec or not spec.is_file():
            spec = open_spec(scene, d, args.frames, args.threads)
        for loop in args.loops:
            log, wall = run_once(scene, spec, d / loop, loop == "closed", args.threads,
                                 args.timeout)
            print(json.dumps(measure(p.name, loop, log, wall), default=float), flush=True)
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())

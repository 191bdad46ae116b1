"""`minority demo`: the whole service on one machine, embedded defaults, no router.

1. oracle: roll the shipped GNS checkpoint out on the demo column (seconds; its first
   frames from the MPM at the model's spacing), derive the
   spec (views, windows, cadence, regions, colormap range), export cameras and a preview;
2. the render server in its own process, listening on loopback, and the closed-loop oracle
   (`minority oracle follow`) beside it: it reads the run's Stats and re-forecasts when the
   run leaves the prediction, the server and ranks following its updates;
3. the MPM column collapse on 2 ranks (MPI), publishing only what the spec asks for, plus
   in situ statistics;
4. frames and the MCAP log from the server; the timing report and the oracle's score;
   a movie of each view and a small animation of it, beside the view's frames.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from minority.oracle_cli import DEFAULT_CHECKPOINT as CHECKPOINT
from minority.sim.columns import ColumnSpec, channel_column_toml

RUN = "demo"


@dataclass(frozen=True)
class DemoOptions:
    out: Path = Path("demo")
    ranks: int = 2
    duration_s: float = 0.7  # simulated; the runout ends near 0.62 s
    cell_size_m: float = 0.016  # 0.016: 12,960 particles (the showcase); 0.032: 1,800
    frames: int = 90  # frame budget, all views
    width: int = 1024  # px
    height: int = 768
    threads: int = 1  # torch and numba threads per process
    checkpoint: Path = CHECKPOINT
    timeout_s: float = 600.0  # the sim's wall-clock limit
    http: str | None = None  # the server's live view, [HOST:]PORT (port 0: a free one)
    follow: bool = True  # run the closed-loop oracle (minority oracle follow) beside the server

    def __post_init__(self) -> None:
        from minority.gns.oracle import OracleOptions
        from minority.render_server.live_http import parse_address

        OracleOptions(frames=self.frames)  # a budget the oracle refuses fails now, not later
        if self.http is not None:
            parse_address(self.http)  # raises ValueError naming the problem


def demo_column(o: DemoOptions) -> str:
    """The showcase column (column_13k's geometry and material) at the demo's resolution;
    the channel and the domain round up to whole cells."""
    cells = lambda m: math.ceil(m / o.cell_size_m - 1e-9) * o.cell_size_m  # noqa: E731
    return channel_column_toml(ColumnSpec(
        length_m=0.144, height_m=0.32, width_m=cells(0.144), domain_length_m=cells(0.8),
        domain_height_m=cells(0.4),
        cell_size_m=o.cell_size_m, youngs_modulus_pa=2.0e6, friction_angle_deg=30.0,
        floor_friction=0.5, side_friction=0.2, duration_s=o.duration_s,
        output_interval_s=0.02), name="demo_column")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Steps:
    """Prints each stage with its wall time."""

    def __init__(self, log=None):
        log = sys.stderr if log is None else log  # the stream of the call, not of the import
        self.log, self.t0 = log, time.perf_counter()

    def __call__(self, text: str) -> None:
        print(f"[demo {time.perf_counter() - self.t0:6.1f} s] {text}", file=self.log, flush=True)


def run_oracle(o: DemoOptions, scene: Path, say: Steps) -> tuple[Path, Path]:
    import torch

    from minority.gns.oracle import Oracle, OracleOptions
    from minority.gns.runtime import tune_allocator
    from minority.preview import preview
    from minority.protocol.paraview import write_pvcc_for_views
    from minority.warmstart import predict_scene

    tune_allocator()
    torch.set_num_threads(o.threads)
    say(f"oracle: the first frames from the MPM, then the GNS ({o.checkpoint.name})")
    p = predict_scene(o.checkpoint, scene, o.duration_s)
    d = o.out / "oracle"
    rollout_h5 = p.write(d, vtk_every=4)
    pos, dt = p.positions, p.frame_interval_s
    say(f"oracle: {pos.shape[1]} particles, {len(pos) - 1} frames in {p.wall_s:.1f} s")
    oracle = Oracle(pos, dt, p.bounds_m, p.spacing_m,
                    OracleOptions(run=RUN, frames=o.frames, width=o.width, height=o.height))
    spec = oracle.spec({"rollout": str(rollout_h5), "checkpoint": str(o.checkpoint)})
    spec_path = o.out / "spec.json"
    spec.save(spec_path)
    write_pvcc_for_views(spec, d / "cameras")
    preview(spec_path, rollout_h5, d / "preview.png")
    s = oracle.summary()
    say(f"oracle: onset {s['onset_s']:.3f} s, peak {s['peak_s']:.3f} s, runout end "
        f"{s['runout_end_s']:.3f} s, displacement up to {s['displacement_range_m'][1]:.3f} m")
    if s.get("standing"):
        say("oracle: no flow predicted: each view renders the start and the end, the rest of "
            "the frames is kept for the follower")
    return spec_path, rollout_h5


def start_follower(o: DemoOptions, scene: Path, endpoint: str, env: dict, log) -> subprocess.Popen:
    """`minority oracle follow` on the run, its update lines to `log`; returns once it
    follows (it has the run's spec, so it reads the run from its first Stats)."""
    follower = subprocess.Popen(
        [sys.executable, "-m", "minority", "oracle", "follow", RUN, "--scene", str(scene),
         "--checkpoint", str(o.checkpoint), "--ranks", str(o.ranks), "--connect", endpoint,
         "--threads", str(o.threads), "--timeout", str(o.timeout_s), "--wait", "120"],
        stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        wait_for_line(Path(log.name), "following run", follower, "the closed-loop oracle", 120)
    except RuntimeError:
        stop(follower)
        raise
    return follower


def wait_for_line(path: Path, text: str, proc: subprocess.Popen, what: str,
                  timeout_s: float = 300.0) -> None:
    """Until `text` is in the file `proc` writes; RuntimeError naming `what` when it exits
    or the time runs out."""
    deadline = time.monotonic() + timeout_s
    while text not in path.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{what} did not start; see {path}")
        time.sleep(0.1)


def stop(proc: subprocess.Popen | None, wait_s: float = 60) -> None:
    """SIGINT a process still running, then kill it if it does not end within wait_s."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()  # never leave it running behind the demo
        proc.wait()


def run_pipeline(o: DemoOptions, scene: Path, spec_path: Path, say: Steps) -> Path:
    """Server process (+ the follower) + sim ranks; returns the server's MCAP log."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log_path = o.out / "run.mcap"
    env = {**os.environ, "OMP_NUM_THREADS": str(o.threads),
           "NUMBA_NUM_THREADS": str(o.threads)}
    live = []
    if o.http is not None:
        from minority.render_server.live_http import parse_address

        host, http_port = parse_address(o.http)
        http_port = http_port or free_port()
        live = ["--http", f"[{host}]:{http_port}" if ":" in host else f"{host}:{http_port}"]
    server_log = open(o.out / "server.log", "w")  # noqa: SIM115 - closed below
    server = subprocess.Popen(
        [sys.executable, "-m", "minority", "serve", "--spec", str(spec_path), "--out",
         str(o.out / "frames"), "--record", str(log_path), "--listen", endpoint,
         "--exit-when-done", *live], stdout=server_log, stderr=subprocess.STDOUT, env=env)
    say(f"render server: pid {server.pid}, listening on {endpoint} (log {o.out / 'server.log'})")
    if live:
        url_host = f"[{host}]" if ":" in host else host
        say(f"live view: http://{url_host}:{http_port}/ (open it now: the server stops when "
            "the run is rendered)")
    follower, follow_log = None, None
    try:
        if o.follow:
            follow_log = open(o.out / "follow.log", "w")  # noqa: SIM115 - closed below
            follower = start_follower(o, scene, endpoint, env, follow_log)
            say(f"closed-loop oracle: pid {follower.pid}, following run {RUN!r} (updates in "
                f"{o.out / 'follow.log'})")
        sim = subprocess.run(
            [sys.executable, "-m", "minority", "sim", str(scene), "--ranks", str(o.ranks),
             "--run", RUN, "--spec", str(spec_path), "--connect", endpoint, "--wait", "30",
             "--out",
             str(o.out / "sim.h5"), "--threads", str(o.threads)],
            env=env, timeout=o.timeout_s)
        if sim.returncode != 0:
            raise RuntimeError(f"the simulation failed (exit {sim.returncode})")
        say("simulation done; waiting for the server to render the last steps")
        server.wait(timeout=120)
        if follower is not None:  # it ends with the run's end, which the server announced
            follower.wait(timeout=60)
    finally:
        stop(server)
        stop(follower)
        server_log.close()
        if follow_log is not None:
            follow_log.close()
    if server.returncode != 0:
        raise RuntimeError(f"the render server failed (exit {server.returncode}); see "
                           f"{o.out / 'server.log'}")
    return log_path


def main(o: DemoOptions) -> int:
    from minority.movie import frame_folders, write_movies
    from minority.protocol.runlog import log_specs
    from minority.report import report
    from minority.score import load_run, markdown, score

    say = Steps()
    o.out.mkdir(parents=True, exist_ok=True)
    scene = o.out / "scene.toml"
    scene.write_text(demo_column(o))
    spec_path, rollout_h5 = run_oracle(o, scene, say)
    log_path = run_pipeline(o, scene, spec_path, say)
    (o.out / "report.md").write_text(report(log_path, o.out))
    specs = log_specs(log_path)  # the last in force: the follower's, if it updated the spec
    result = score(specs[-1], load_run(log_path))
    updates = [s.provenance for s in specs if "update" in s.provenance]
    if o.follow:
        say(f"closed-loop oracle: {len(updates)} spec updates "
            f"({sum(u.get('kind') == 'forecast' for u in updates)} re-forecasts)")
    (o.out / "score.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    (o.out / "score.md").write_text(markdown(result))
    write_movies(frame_folders(o.out / "frames" / RUN), o.out / "frames" / RUN,
                 progress=say)
    say("done")
    print(markdown(result))
    print(WHERE.format(out=o.out, run=RUN))
    return 0


WHERE = """Files (in {out}/):
  scene.toml            the simulated column (sim/README.md explains the keys)
  oracle/rollout.h5     the GNS prediction; oracle/vtk/rollout.pvd opens it in ParaView
  oracle/cameras/*.pvcc the spec's cameras for ParaView (View > Camera > Load)
  oracle/preview.png    the spec's views rendered on the prediction
  spec.json             the oracle spec the run started with (edit it and replay the log)
  follow.log            the closed-loop oracle's spec updates, a JSON line each: reason,
                        kind (shift, forecast, end), the run's time, wall cost (absent: --no-follow)
  frames/{run}/VIEW/*.png  the frames the render server ray-traced during the run
  frames/{run}/VIEW.mp4    those frames as a movie (H.264, one per frame at 10 fps)
  frames/{run}/VIEW.webp   a small looping animation of them (320 px wide, under 1 MB)
  run.mcap              every message of the run (minority replay / report, MCAP viewers)
  sim.h5                the MPM run's own output frames
  report.md + *.png     receive / setup / render times per step and view
  score.md, score.json  the oracle's predictions against what the run did
"""

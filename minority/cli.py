"""The `minority` command: argument parsing only; the work lives in the packages."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

NOT_BUILT = 2  # exit status of a subcommand that is not built yet


def _not_built(name: str):
    def run(args: argparse.Namespace) -> int:
        print(f"minority {name}: not built yet", file=sys.stderr)
        return NOT_BUILT
    return run


def _add_network(p: argparse.ArgumentParser) -> None:
    from protocol.session import add_network_args
    add_network_args(p)


def _cmd_record(args: argparse.Namespace) -> int:
    import zenoh
    from mcap.writer import CompressionType

    from protocol.log import Recorder
    from protocol.session import Role, open_session, options_from_args

    opts = options_from_args(args)
    opts.connect_timeout_s = args.wait
    role = Role.SERVER if args.listen else Role.CLIENT  # --listen: sims may connect to us
    try:
        session = open_session(opts, role)
    except zenoh.ZError as exc:
        where = ", ".join(opts.connect) or "the default endpoint"
        print(f"minority record: cannot reach a zenoh peer at {where} within {args.wait:g} s "
              f"(start `minority serve` first, or pass --connect): {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    recorder = Recorder(session, args.output, run=args.run,
                        compression=CompressionType[args.compression.upper()],
                        flush_interval_s=args.flush_interval)
    print(f"recording minority/{args.run}/** to {args.output} (Ctrl-C to stop)", file=sys.stderr)
    start = time.monotonic()
    try:
        while not stop.wait(1.0):
            elapsed = time.monotonic() - start
            if not args.quiet:
                print(f"\r{elapsed:7.0f} s  {recorder.written} messages written  "
                      f"{recorder.dropped} dropped", end="", file=sys.stderr)
            if args.duration and elapsed >= args.duration:
                break
    finally:
        recorder.close()
        session.close()
    print(f"\n{recorder.written} messages written to {args.output} "
          f"({recorder.writer.rejected} rejected as malformed, {recorder.dropped} dropped)",
          file=sys.stderr)
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    import zenoh

    from protocol.errors import SpecError
    from protocol.session import Role, open_session, options_from_args
    from protocol.spec import Spec
    from render_server.daemon import RenderServer, ServerOptions

    try:
        spec = Spec.load(args.spec)
    except (SpecError, OSError) as exc:
        print(f"minority serve: error: {exc}", file=sys.stderr)
        return 1
    record = None if args.no_record else (args.record or args.out / f"{spec.run}.mcap")
    if record is not None:
        record.parent.mkdir(parents=True, exist_ok=True)
    try:
        session = open_session(options_from_args(args), Role.SERVER)
    except zenoh.ZError as exc:
        print(f"minority serve: cannot open the zenoh session: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    server = RenderServer(session, ServerOptions(spec, args.out, record, args.timeout,
                                                 shadows=args.shadows))
    print(f"serving run {spec.run!r}: {len(spec.views)} views, frames to {args.out}/{spec.run}/"
          + (f", log {record}" if record else ""), file=sys.stderr, flush=True)
    try:
        stop.wait()
    finally:
        server.close()
        session.close()
    print(f"stopped: {server.summary()}", file=sys.stderr)
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    from sim.driver import SimulationError
    from sim.runner import run_scene
    from sim.scene import SceneError, builtin_scene_path

    try:
        scene = Path(args.scene)
        if not scene.exists() and scene.suffix == "":
            scene = builtin_scene_path(args.scene)
        out = args.out or Path(f"{scene.stem}.h5")
        summary = run_scene(scene, out, dt=args.dt, threads=args.threads,
                            progress=not args.quiet)
    except (SceneError, SimulationError, ValueError, OSError) as exc:
        print(f"minority sim: error: {exc}", file=sys.stderr)
        return 1
    print(f"{summary.particles} particles, {summary.steps} steps, {summary.frames} frames, "
          f"{summary.sim_time_s:.3f} s simulated in {summary.wall_s:.1f} s wall "
          f"({summary.particle_steps_per_s:.3g} particle-steps/s) -> {summary.out_path}",
          file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="minority",
        description="In situ visualization of particle simulations, steered by a graph "
                    "network oracle. Units: metres, seconds, kilograms, pascals, degrees.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("serve", help="run the render server daemon",
                       description="Run the render server until SIGINT/SIGTERM: serve the spec "
                                   "on minority/{run}/spec, receive chunks, assemble steps, "
                                   "ray-trace the scheduled views to DIR/{run}/{view}/"
                                   "{step:06d}.png, publish frames and timing, record every "
                                   "message of the run to MCAP.")
    p.add_argument("--spec", type=Path, required=True, help="oracle spec JSON file")
    p.add_argument("--out", type=Path, default=Path("frames"), metavar="DIR",
                   help="frame directory (default: frames)")
    p.add_argument("--record", type=Path, metavar="FILE.mcap",
                   help="MCAP log of the run (default: DIR/{run}.mcap)")
    p.add_argument("--no-record", action="store_true", help="do not write an MCAP log")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="render a step with what arrived S seconds after its first chunk "
                        "(default 5)")
    p.add_argument("--shadows", action="store_true", help="cast shadow rays (slower)")
    _add_network(p)
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("sim", help="run the MPM simulation of a scene",
                       description="Run the 3D MLS-MPM simulation (Drucker-Prager sand) of a "
                                   "scene and write its frames to HDF5 (positions m, "
                                   "velocities m/s, displacements m, float32).")
    p.add_argument("scene", help="scene TOML file (keys and units in sim/README.md), or the "
                                 "name of a shipped scene: tiny, cylinder_small, column_13k, "
                                 "column_100k, column_1m")
    p.add_argument("--out", type=Path, help="output HDF5 file (default: SCENE_NAME.h5)")
    p.add_argument("--dt", type=float, metavar="S",
                   help="fixed time step in s; refused if above the CFL bound (default: the "
                        "CFL step, recomputed every step)")
    p.add_argument("--threads", type=int, metavar="N", help="numba threads (default: all cores)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_cmd_sim)

    from minority.oracle_cli import add_oracle_parser
    add_oracle_parser(sub)

    p = sub.add_parser("replay", help="re-render or re-publish a recorded MCAP log",
                       description="Re-render a recorded run with a new spec, or re-publish it.")
    p.add_argument("log", type=Path, help="MCAP file written by `minority record` or `serve`")
    _add_network(p)
    p.set_defaults(func=_not_built("replay"))

    p = sub.add_parser("report", help="timing tables and oracle scores from a log",
                       description="Turn an MCAP log into timing tables and plots.")
    p.add_argument("log", type=Path, help="MCAP file")
    p.set_defaults(func=_not_built("report"))

    p = sub.add_parser("record", help="record every minority message to MCAP",
                       description="Subscribe to minority/{run}/** and write every message to an "
                                   "MCAP file (chunks byte-for-byte, frames as images, timing "
                                   "as JSON) until Ctrl-C, SIGTERM or --duration.")
    p.add_argument("-o", "--output", type=Path, default=Path("minority.mcap"),
                   help="MCAP file to write (default: minority.mcap)")
    p.add_argument("--run", default="*", help="record one run id only (default: every run)")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="stop after S seconds (default: run until stopped)")
    p.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="keep trying to reach the server for S seconds at start (default 10)")
    p.add_argument("--compression", choices=["none", "lz4", "zstd"], default="none",
                   help="MCAP chunk compression (default none: particle floats compress poorly)")
    p.add_argument("--flush-interval", type=float, default=0.5, metavar="S",
                   help="close an MCAP chunk at least every S seconds, so a killed recorder "
                        "loses at most that much (default 0.5)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    _add_network(p)
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("demo", help="the whole pipeline on one machine, embedded defaults",
                       description="Oracle rollout, spec, render server, 2-rank sim, frames, "
                                   "log, report and score, on one machine.")
    p.set_defaults(func=_not_built("demo"))
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

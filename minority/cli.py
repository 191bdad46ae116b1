"""The `minority` command: argument parsing only; the work lives in the packages.

Each command is a parser builder (`_serve_parser`) beside its handler (`_cmd_serve`);
`build_parser` composes them, with `oracle`, `log` and `deploy` from their own modules. The
conventions every command keeps (-o/--out, defaults in --help, exit statuses) are in
minority/cliargs.py.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path

from minority.cliargs import BAD_INPUT, FAILED, HelpFormatter, add_out, command, fail, missing, parent_made
from minority.signals import stop_on_signals

DEFAULT_REBALANCE_EVERY = 100  # steps; sim.decomp.DEFAULT_REBALANCE_EVERY (not imported here)
# packages whose numba kernels are cached on disk (cache=True): their stale caches are dropped
# before a command that runs kernels (protocol.jitcache), never at import time
NUMBA_PACKAGES = ("minority.sim", "minority.insitu", "minority.gns", "minority.render_server")
NO_MPI = ("no MPI library: install the mpich wheel (pip install 'minority[mpi]', what `make` "
          "does) or mpi4py built against your system's MPI (deploy/README.md, 'A cluster's own MPI')")


def _add_network(p: argparse.ArgumentParser) -> None:
    from minority.protocol.session import add_network_args
    add_network_args(p)


def _open_peer(opts, role, command: str, wait_s: float):
    """A zenoh session, or None after saying in one line why no peer was reached."""
    import zenoh

    from minority.protocol.auth import CredentialsError, credentials_dir
    from minority.protocol.session import open_session

    try:
        return open_session(opts, role)
    except CredentialsError as exc:
        print(f"minority {command}: error: {exc}", file=sys.stderr)
        return None
    except zenoh.ZError as exc:
        where = ", ".join(opts.connect) or "the default endpoint"
        print(f"minority {command}: cannot reach a zenoh peer at {where} within {wait_s:g} s "
              f"(start `minority serve` first, or pass --connect; a server of another user, "
              f"or one whose password is not in {credentials_dir()}, refuses the link): {exc}",
              file=sys.stderr)
        return None


# --- serve ------------------------------------------------------------------------------

def _serve_parser(sub) -> None:
    p = command(sub, "serve", help="run the render server daemon",
                description="Run the render server until SIGINT/SIGTERM: serve each spec on "
                            "minority/{run}/spec, receive chunks, assemble steps, ray-trace "
                            "the scheduled views to DIR/{run}/{view}/{step:06d}.png, publish "
                            "frames and timing, record every message of the run to MCAP. A "
                            "run id may run again (a new sim after the last one ended, or a "
                            "server restart): each run gets the first free name of {run}, "
                            "{run}.1, ... for its frames and log, so nothing is overwritten. "
                            "Exit status 2 on a bad spec, 1 when the server cannot start.")
    p.add_argument("--spec", type=Path, required=True, action="append",
                   help="oracle spec JSON file; repeat it to serve several runs at once")
    add_out(p, "frame directory", default=Path("frames"), metavar="DIR")
    p.add_argument("--record", type=Path, metavar="FILE.mcap",
                   help="MCAP log of the run (one spec only; default: DIR/{run}.mcap); a "
                        "later run or an existing file gets FILE.1.mcap, ...")
    p.add_argument("--no-record", action="store_true", help="do not write an MCAP log")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="render a step with what arrived S seconds after its first chunk")
    p.add_argument("--shadows", action="store_true", help="cast shadow rays (slower)")
    p.add_argument("--exit-when-done", action="store_true",
                   help="exit once every rank of each run is done and its last step rendered "
                        "(for batch jobs and the demo; without it: serve until stopped)")
    p.add_argument("--http", metavar="[HOST:]PORT",
                   help="also serve a live view to a browser at http://HOST:PORT/ (HOST "
                        "left out: 127.0.0.1; PORT 0: a free one; the URL is printed): the "
                        "newest frame of every view as it is rendered, the ranks' stats "
                        "against the spec's predicted events, per-step receive/setup/render "
                        "times, and an index of DIR's runs (frames, movies, reports, scores, "
                        "read-only). No password: name another address than loopback only "
                        "on a trusted network (default: off)")
    g = p.add_argument_group("several render ranks (MPI)")
    g.add_argument("--ranks", type=int, metavar="N",
                   help="render ranks (default: 1, or what the MPI launcher started). N > 1 "
                        "re-runs this command under the venv's mpiexec -n N. Sim rank r's "
                        "chunks go to render rank r %% N, "
                        "which logs them to its own shard next to the log (FILE.render{k}.mcap"
                        "; replay, report and score read the shards with it); rank 0 serves "
                        "the spec, assembles the steps, writes the frames, publishes frames, "
                        "timing and events; all ranks render each step together. One --spec, "
                        "no --shadows")
    g.add_argument("--max-sim-ranks", type=int, default=256, metavar="M",
                   help="with N render ranks: subscribe to the chunks of sim ranks 0..M-1 "
                        "(an error event says when a sim has more)")
    g.add_argument("--rank-timeout", type=float, default=5.0, metavar="S",
                   help="with N render ranks: a rank that sends no heartbeat for S seconds is "
                        "dead; rank 0 then records an error event, ends the run (its log "
                        "closed) and exits with status 1; the others exit when rank 0 is "
                        "silent that long")
    _add_network(p)
    p.set_defaults(func=_cmd_serve, kernels=True)


def _keep_ranks_alive(mpiexec) -> list[str]:
    """Hydra's flag that keeps the other ranks alive when one exits with an error status
    (minority.rank_guard turns a rank's death by a signal into one), so that rank 0 can
    record the failure and close its log; nothing for another launcher."""
    try:
        version = subprocess.run([str(mpiexec), "--version"], capture_output=True, text=True,
                                 timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return ["-disable-auto-cleanup"] if "HYDRA" in version else []


def _cmd_serve(args: argparse.Namespace) -> int:
    # only light imports until the command is relaunched or guarded (a guard holds no more)
    from minority import rank_guard
    from minority.protocol.errors import SpecError
    from minority.protocol.spec import Spec
    from minority.sim.launcher import relaunch, under_launcher

    if args.ranks is not None and args.ranks < 1:
        return fail("serve", "--ranks must be at least 1", BAD_INPUT)
    if args.max_sim_ranks < 1 or not args.rank_timeout > 0:
        return fail("serve", "--max-sim-ranks must be at least 1 and --rank-timeout above 0",
                    BAD_INPUT)
    if (args.ranks or 1) > 1 and (len(args.spec) > 1 or args.shadows):
        return fail("serve", "several render ranks serve one --spec, without --shadows (a "
                             "shadow ray crosses every rank's bricks)", BAD_INPUT)
    try:
        specs = [Spec.load(path) for path in args.spec]
    except (SpecError, OSError) as exc:
        return fail("serve", exc, BAD_INPUT)
    if not under_launcher() and (args.ranks or 1) > 1:  # the same command under mpiexec
        return relaunch(args.ranks, args.argv, "serve", _keep_ranks_alive)
    if under_launcher() and rank_guard.wanted():
        # this command again, as the guard's child; the guard exits with its status
        rank_guard.run(args.argv, grace_s=args.rank_timeout + 5.0)
    if under_launcher():
        try:
            from mpi4py import MPI
        except (ImportError, RuntimeError) as exc:
            return fail("serve", f"{NO_MPI} (mpi4py: {str(exc).splitlines()[0] if str(exc) else exc!r})")
        size = MPI.COMM_WORLD.Get_size()
        if args.ranks is not None and args.ranks != size:
            return fail("serve", f"--ranks {args.ranks}, but the launcher started {size} "
                                 "processes", BAD_INPUT)
        if size > 1:
            if len(specs) > 1 or args.shadows:
                return fail("serve", "several render ranks serve one --spec, without "
                                     "--shadows", BAD_INPUT)
            from minority.serve_ranks import serve_ranks
            return serve_ranks(args, specs[0], MPI.COMM_WORLD)
    import zenoh

    from minority.protocol.session import Role, open_session, options_from_args, shm_pool_for
    from minority.render_server.daemon import RenderServer, ServerOptions
    from minority.serve_ranks import end_line, report_failures

    runs = [s.run for s in specs]
    if len(set(runs)) < len(runs):
        return fail("serve", f"two specs name the same run ({', '.join(runs)}); a server "
                             "serves each run id once", BAD_INPUT)
    if args.record and len(specs) > 1:
        return fail("serve", "--record names one log: with several specs each run logs to "
                             "DIR/{run}.mcap", BAD_INPUT)
    live = None
    if args.http is not None:  # bound before anything starts: a bad address exits at once
        from minority.render_server.live import LiveView
        from minority.render_server.live_http import parse_address
        try:
            live = LiveView(args.out, *parse_address(args.http))
        except ValueError as exc:
            return fail("serve", exc, BAD_INPUT)
        except OSError as exc:
            return fail("serve", f"--http {args.http}: cannot listen there: "
                                 f"{exc.strerror or exc}", BAD_INPUT)
        print(f"live view: {live.url}" + ("" if live.loopback else
              " (no password: anyone who can reach this address sees the runs and DIR)"),
              file=sys.stderr, flush=True)
    opts = options_from_args(args)
    # the server's own large puts are frames: a pool for the largest raw image
    opts.shm_pool_bytes = shm_pool_for(max((3 * v.width * v.height for s in specs
                                            for v in s.views), default=0) + 65536)
    try:
        session = open_session(opts, Role.SERVER)
    except (zenoh.ZError, OSError) as exc:
        print(f"minority serve: cannot open the zenoh session: {exc}", file=sys.stderr)
        if live is not None:
            live.close()
        return FAILED
    servers = []
    stop = stop_on_signals()  # before the "serving" lines: a stop from then on is clean
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for spec in specs:
            record = None if args.no_record else (args.record or args.out / f"{spec.run}.mcap")
            if record is not None:
                parent_made(record)
            servers.append(RenderServer(session, ServerOptions(
                spec, args.out, record, args.timeout, shadows=args.shadows,
                observer=live.observe if live is not None else None)))
            run = servers[-1].current
            print(f"serving run {spec.run!r}: {len(spec.views)} views, frames to "
                  f"{run.frames_dir}/" + (f", log {run.writer.path}" if run.writer else ""),
                  file=sys.stderr, flush=True)
    except OSError as exc:
        print(f"minority serve: error: cannot start: {exc}", file=sys.stderr)
        for s in servers:
            s.close()
        session.close()
        if live is not None:
            live.close()
        return FAILED
    try:
        while not stop.wait(0.2):
            if args.exit_when_done and all(s.finished.is_set() for s in servers):
                print(end_line(servers), file=sys.stderr)
                break
    finally:
        for s in servers:
            s.close()
        session.close()
        if live is not None:
            live.close()
    for s in servers:
        print(f"stopped: {s.summary()}", file=sys.stderr)
    if live is not None and live.dropped:
        print(f"live view: {live.dropped} updates dropped for slow browsers", file=sys.stderr)
    return report_failures(servers)


# --- sim --------------------------------------------------------------------------------

def _sim_parser(sub) -> None:
    p = command(sub, "sim", help="run the MPM simulation of a scene",
                description="Run the 3D MLS-MPM simulation (Drucker-Prager sand) of a scene "
                            "and write its frames to HDF5 (positions m, velocities m/s, "
                            "displacements m, float32). Exit status 2 on a bad scene, spec or "
                            "argument, 1 when the run fails, 130 or 143 when SIGINT or SIGTERM "
                            "stopped it (at a step boundary: frames so far, records and "
                            "rank_done events complete).")
    p.add_argument("scene", help="scene TOML file (keys and units in sim/README.md), or the "
                                 "name of a shipped scene: tiny, cylinder_small, column_13k, "
                                 "column_100k, column_1m")
    add_out(p, "output HDF5 file (default: SCENE_NAME.h5)", metavar="FILE.h5")
    p.add_argument("--dt", type=float, metavar="S",
                   help="fixed time step in s; refused if above the CFL bound (default: the "
                        "CFL step, recomputed every step)")
    p.add_argument("--threads", type=int, metavar="N",
                   help="numba threads per rank (default: the node's cores / its ranks)")
    p.add_argument("--ranks", type=int, metavar="N",
                   help="MPI ranks: slabs of the grid along x (default: 1, or what the MPI "
                        "launcher started); N > 1 re-runs this command under mpiexec -n N")
    p.add_argument("--rebalance-every", type=int, default=DEFAULT_REBALANCE_EVERY, metavar="K",
                   help="move the slab boundaries to balance the particle count every K steps "
                        "(0: never)")
    p.add_argument("--steps", type=int, metavar="N",
                   help="stop after N steps (default: at the scene's duration)")
    p.add_argument("--run", metavar="ID",
                   help="run id of the keys minority/ID/...: the run of the server's spec "
                        "(default: the scene's name)")
    p.add_argument("--spec", type=Path, metavar="FILE",
                   help="spec to follow when no server serves one (its run must be the run id)")
    p.add_argument("--record", type=Path, metavar="FILE.mcap",
                   help="also write what the ranks publish to MCAP (rank 0: FILE.mcap, rank "
                        "r > 0: FILE.rank{r}.mcap)")
    p.add_argument("--wait", type=float, default=0.0, metavar="S",
                   help="keep trying to reach the server for S seconds at start (0: one try; "
                        "without a server the sim runs on and says so)")
    p.add_argument("--no-publish", action="store_true",
                   help="no network: do not look for a server, publish or record")
    p.add_argument("--stats-every-s", type=float, default=0.005, metavar="S",
                   help="each rank publishes flow statistics (speed histograms, kinetic energy, "
                        "displacement; for the oracle's score) every S s of simulated time "
                        "(0: none)")
    p.add_argument("--no-context", action="store_true",
                   help="send only the particles in the spec's regions: the server draws "
                        "nothing outside them (default: the particles outside are sent once, "
                        "and again when they move, for the server to draw from its cache)")
    p.add_argument("--context-tolerance", type=float, default=0.0, metavar="M",
                   help="resend a particle outside the regions once it moved this far, m "
                        "(0: at any motion, frames equal full frames)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    _add_network(p)
    p.set_defaults(func=_cmd_sim, kernels=True)


def _mpi():
    """mpi4py's MPI module, or None after saying which MPI to install."""
    try:
        from mpi4py import MPI
    except (ImportError, RuntimeError) as exc:  # mpi4py finds no libmpi: RuntimeError
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        fail("sim", f"{NO_MPI} (mpi4py: {reason})")
        return None
    return MPI


def _sim_bad_input(args: argparse.Namespace) -> str | None:
    """What is wrong with `minority sim`'s arguments, checked before any rank starts (the
    scene and the spec are read in full); None when nothing is."""
    import math

    from minority.protocol.check import NAME_RE
    from minority.protocol.errors import SpecError
    from minority.protocol.spec import Spec
    from minority.sim.scene import SceneError, load_scene, scene_path

    numbers = (("--ranks", args.ranks, 1), ("--threads", args.threads, 1),
               ("--steps", args.steps, 0), ("--rebalance-every", args.rebalance_every, 0))
    for flag, value, least in numbers:
        if value is not None and value < least:
            return f"{flag} must be at least {least}, got {value}"
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0.0):
        return f"--dt must be a finite time step > 0 s, got {args.dt}"
    for flag, value, unit in (("--wait", args.wait, "seconds"),
                              ("--stats-every-s", args.stats_every_s, "seconds"),
                              ("--context-tolerance", args.context_tolerance, "metres")):
        if not (math.isfinite(value) and value >= 0.0):
            return f"{flag} must be a finite number of {unit} >= 0, got {value}"
    if args.run is not None and not NAME_RE.match(args.run):
        return (f"--run {args.run!r}: a run id is 1-64 characters of A-Za-z0-9_.- starting "
                "with a letter, digit or underscore")
    if args.record is not None and not args.no_publish and args.record.exists():
        return f"--record {args.record}: the file exists (a record is never overwritten)"
    try:
        load_scene(scene_path(args.scene))
        if args.spec is not None:
            Spec.load(args.spec)
    except (SceneError, SpecError) as exc:
        return str(exc)
    except OSError as exc:  # the spec file: missing, a directory, unreadable
        return f"cannot read spec file {args.spec}: {exc.strerror or exc}"
    return None


def _cmd_sim(args: argparse.Namespace) -> int:
    from minority.sim.launcher import StopSignals, relaunch, stopped_status, under_launcher

    bad = _sim_bad_input(args)  # before any rank starts (and again on each rank)
    if bad is not None:
        return fail("sim", bad, BAD_INPUT)
    if not under_launcher() and (args.ranks or 1) > 1:
        return relaunch(args.ranks, args.argv)  # the same command under mpiexec -n RANKS
    # SIGINT, SIGTERM: stop at the next step, close, 130/143 (a second one: see StopSignals)
    with StopSignals(repeat_ends=not under_launcher()) as stop:
        status = _run_sim(args, stop)
    return stopped_status(stop.signum) if stop.signum and status == 0 else status


def _run_sim(args: argparse.Namespace, stop) -> int:
    """`minority sim` on this process's rank, its arguments checked; `stop` is polled at
    every step (sim.launcher.StopSignals)."""
    from minority.sim.driver import SimulationError
    from minority.sim.ranks import RankRunConfig, run_ranks, warning_block
    from minority.sim.scene import SceneError, scene_path

    scene = scene_path(args.scene)
    MPI = _mpi()
    if MPI is None:
        return FAILED
    if args.ranks is not None and args.ranks != MPI.COMM_WORLD.Get_size():
        return fail("sim", f"--ranks {args.ranks}, but the launcher started "
                           f"{MPI.COMM_WORLD.Get_size()} processes", BAD_INPUT)
    try:
        publish = None
        if not args.no_publish:
            from minority.insitu.publisher import PublishOptions
            from minority.protocol.session import options_from_args

            record = parent_made(args.record) if args.record else None
            try:
                publish = PublishOptions(network=options_from_args(args), spec_file=args.spec,
                                         record=record, stats_every_s=args.stats_every_s,
                                         context=not args.no_context,
                                         context_tolerance_m=args.context_tolerance)
            except ValueError as exc:
                return fail("sim", exc, BAD_INPUT)
        out = parent_made(args.out or Path(f"{scene.stem}.h5"))
        config = RankRunConfig(scene_path=scene, out=out,
                               dt=args.dt, threads=args.threads,
                               rebalance_every=args.rebalance_every, progress=not args.quiet,
                               publish=publish, run=args.run, wait_s=args.wait,
                               max_steps=args.steps, stop=stop)
        summary = run_ranks(config)
    except SceneError as exc:
        return fail("sim", exc, BAD_INPUT)
    except (SimulationError, ValueError, OSError) as exc:
        return fail("sim", exc)
    if MPI.COMM_WORLD.Get_rank() == 0:
        slabs = (f", {summary.rebalances} rebalances, {summary.migrated} particles migrated"
                 if summary.ranks > 1 else "")
        p = summary.publish
        sent = (f"; run {summary.run}: {p['sent']} of {p['scheduled']} chunks sent, "
                f"{p['dropped']} dropped" if p else "")
        stopped = (f" (stopped by {signal.Signals(summary.stopped).name})"
                   if summary.stopped else "")
        print(f"{summary.particles} particles, {summary.ranks} rank(s), {summary.steps} steps"
              f"{stopped}, {summary.frames} frames, {summary.sim_time_s:.3f} s simulated in "
              f"{summary.wall_s:.1f} s wall ({summary.particle_steps_per_s:.3g} "
              f"particle-steps/s{slabs}) -> {summary.out_path}{sent}", file=sys.stderr)
        if summary.not_published:
            print(warning_block([f"this run was NOT published/observed: "
                                 f"{summary.not_published}"]), file=sys.stderr)
    return 0


# --- replay -----------------------------------------------------------------------------

def _replay_parser(sub) -> None:
    from minority.movie import DEFAULT_FPS

    p = command(sub, "replay", help="re-render, export or re-publish a recorded MCAP log",
                description="Re-render the chunks of a recorded run with the log's own spec "
                            "(its last) or a new one into DIR/{view}/{step:06d}.png (the "
                            "daemon's renderer: the log's spec gives the same pixels); views "
                            "needing data the log does not hold (a field, particles culled "
                            "away, steps never recorded) are reported, not rendered. --vtk "
                            "exports the steps for ParaView; --publish re-sends the chunks to "
                            "a running `minority serve`; --movie makes DIR/{view}.mp4 and "
                            "DIR/{view}.webp of every view (without --spec from the frames the "
                            "server logged, written to DIR/{view}/ and not re-rendered). Exit "
                            "status 2 on bad input (no such log, a bad spec, no frames for any "
                            "view), 1 when a file, ffmpeg or the network fails.")
    p.add_argument("log", type=Path, metavar="RUN.mcap",
                   help="MCAP file written by `minority serve` or `minority record`")
    p.add_argument("--spec", type=Path, metavar="FILE",
                   help="spec JSON to render with (default: the last spec in the log)")
    add_out(p, "frame directory (default: RUN-replay beside the log); frames are written "
               "when --out or --movie is given or neither --vtk nor --publish is",
            metavar="DIR")
    p.add_argument("--vtk", type=Path, metavar="DIR",
                   help="write every recorded step as DIR/{run}_{step:06d}.vtp (all recorded "
                        "fields as point data) plus DIR/{run}.pvd with the simulated times")
    p.add_argument("--publish", action="store_true",
                   help="re-publish the recorded chunks and spec to a running render server "
                        "instead of rendering")
    p.add_argument("--rate", type=float, default=1.0, metavar="R",
                   help="with --publish: pace of the recorded log times (2: twice as fast, "
                        "0: as fast as possible)")
    p.add_argument("--run", metavar="ID",
                   help="the run to replay when the log holds several (default: the run of "
                        "its last spec)")
    p.add_argument("--shadows", action="store_true",
                   help="cast shadow rays (as `minority serve --shadows` did)")
    p.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="with --publish: wait S seconds for the server")
    p.add_argument("--movie", action="store_true",
                   help="also write DIR/{view}.mp4 (H.264, yuv420p; odd sides padded to even "
                        "by repeating the last row or column, never cropped) and a small "
                        "looping animation DIR/{view}.webp (320 px wide, at most 40 frames, "
                        "under 1 MB: for a README or a web page) of each view's frames in "
                        "step order; without --spec the frames are those the server logged "
                        "(a log without frames is re-rendered with its own spec)")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS, metavar="N",
                   help="with --movie: frames per second of the movies; one movie frame per "
                        "rendered frame, whatever the schedule's cadence, so movie time is "
                        "not simulated time when a view's cadence changes between windows")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    _add_network(p)
    p.set_defaults(func=_cmd_replay, kernels=True)


def _cmd_replay(args: argparse.Namespace) -> int:
    from minority.protocol.errors import ProtocolError, SpecError
    from minority.protocol.runlog import RunLogError
    from minority.replay import replay

    if args.rate < 0:
        return fail("replay", "--rate must be 0 (as fast as possible) or positive", BAD_INPUT)
    if not args.fps > 0:
        return fail("replay", f"--fps must be positive, not {args.fps:g}", BAD_INPUT)
    if not args.log.is_file():
        return fail("replay", f"{args.log}: no such file", BAD_INPUT)
    if args.publish:
        if args.spec or args.out or args.vtk or args.movie:
            print("minority replay: --publish re-sends the chunks only; the server renders them "
                  "with its own spec (--spec, --out, --vtk, --movie ignored)", file=sys.stderr)
        return _replay_publish(args)
    from minority.movie import MovieError
    from minority.protocol.spec import Spec
    from minority.replay import replay_movies

    out = args.out
    if out is None and (args.vtk is None or args.movie):
        out = args.log.parent / f"{args.log.stem}-replay"
    progress = None if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
    try:
        spec = Spec.load(args.spec) if args.spec else None
        if args.movie:
            summary = replay_movies(args.log, spec, out, args.vtk, args.run, args.shadows,
                                    args.fps, progress=progress)
        else:
            summary = replay(args.log, spec, out, args.vtk, args.run, args.shadows, progress)
    except (RunLogError, SpecError, ProtocolError, MovieError) as exc:
        return fail("replay", exc, BAD_INPUT)
    except (OSError, RuntimeError) as exc:  # a file that cannot be written; ffmpeg failing
        return fail("replay", exc)
    print(summary.text())
    return 0


def _replay_publish(args: argparse.Namespace) -> int:
    from minority.protocol.errors import ProtocolError
    from minority.protocol.republish import NoServer
    from minority.protocol.runlog import RunLogError
    from minority.protocol.session import Role, options_from_args
    from minority.replay import publish

    opts = options_from_args(args)
    opts.connect_timeout_s = args.wait
    session = _open_peer(opts, Role.SERVER if args.listen else Role.CLIENT, "replay", args.wait)
    if session is None:
        return FAILED
    stop = stop_on_signals()
    try:
        s = publish(args.log, session, args.rate, args.run, args.wait, stop)
    except (RunLogError, ProtocolError) as exc:
        return fail("replay", exc, FAILED if isinstance(exc, NoServer) else BAD_INPUT)
    finally:
        session.close()
    print(f"run {s.run}: re-published {s.chunks} chunks and {s.specs} specs "
          f"({s.log_s:.3f} s of log time in {s.wall_s:.3f} s)")
    return 0


# --- report, report score ---------------------------------------------------------------

def _report_parser(sub) -> None:
    # `minority report RUN.mcap` reports a log; `minority report score SPEC RUN.mcap` (the
    # oracle score) is its sibling with its own parser (`score_parser`), chosen in `main`
    p = command(sub, "report", help="timing tables and oracle scores from a log",
                description="Turn the MCAP log of a run (written by `minority serve`) into "
                            "markdown on stdout: mean receive / setup / render time per in "
                            "situ step and per view (ms, and % of the total), frames per view, "
                            "bytes received vs a full dump (MB = 1e6 bytes), skipped and "
                            "incomplete steps; and two PNG plots, LOG_STEM.timing.png and "
                            "LOG_STEM.bytes.png. Exit status 2 on bad input (no such file, "
                            "not MCAP, no timing records), 1 when a file cannot be read or "
                            "written. `minority report score SPEC.json RUN.mcap [-o DIR]`: the "
                            "oracle's predictions against the run (see `minority report score "
                            "--help`).")
    p.add_argument("log", metavar="RUN.mcap", help="MCAP log of the run")
    add_out(p, "directory for the PNG plots (default: the log's directory)", metavar="DIR")
    p.add_argument("--no-plots", action="store_true", help="write no PNG, only the markdown")
    p.add_argument("--run", metavar="ID",
                   help="the run to report when the log holds timing of several runs "
                        "(default: the only one)")
    p.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    from minority.protocol.runlog import RunLogError
    from minority.report import report

    try:
        text = report(Path(args.log), args.out, not args.no_plots, args.run)
    except RunLogError as exc:
        return fail("report", exc, BAD_INPUT)
    except OSError as exc:
        return fail("report", exc)
    print(text, end="")
    return 0


def score_parser() -> argparse.ArgumentParser:
    """`minority report score` (a word after `report`, so its own parser: argparse cannot
    mix a subcommand with the report's positional log)."""
    p = argparse.ArgumentParser(
        prog="minority report score", formatter_class=HelpFormatter,
        description="Score the oracle's predictions (events, displacement, regions, frames in "
                    "the critical windows, bytes) against the run's in situ statistics "
                    "(Stats messages of its log): markdown on stdout, and score.json with "
                    "--out. Exit status 2 on bad input, 1 when a file cannot be written.")
    p.add_argument("spec", metavar="SPEC.json", help="the oracle spec")
    p.add_argument("log", metavar="RUN.mcap", help="the MCAP log of the run it predicted")
    add_out(p, "also write DIR/score.json and DIR/score.md", metavar="DIR")
    p.set_defaults(func=_cmd_score)
    return p


def _cmd_score(args: argparse.Namespace) -> int:
    import json

    from minority.protocol.errors import ProtocolError, SpecError
    from minority.protocol.runlog import RunLogError
    from minority.protocol.spec import Spec
    from minority.score import load_run, markdown, score

    spec_path, log_path = Path(args.spec), Path(args.log)
    if (status := missing("report score", spec_path, log_path)) is not None:
        return status
    try:
        spec = Spec.load(spec_path)
        result = score(spec, load_run(log_path, spec.run))
    except (RunLogError, SpecError, ProtocolError) as exc:
        return fail("report score", exc, BAD_INPUT)
    except OSError as exc:
        return fail("report score", exc)
    text = markdown(result)
    if args.out:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "score.json").write_text(json.dumps(result, indent=1, default=float)
                                                 + "\n")
            (args.out / "score.md").write_text(text)
        except OSError as exc:
            return fail("report score", exc)
    print(text, end="")
    return 0


# --- record -----------------------------------------------------------------------------

def _record_parser(sub) -> None:
    p = command(sub, "record", help="record every minority message to MCAP",
                description="Subscribe to minority/{run}/** and write every message to an MCAP "
                            "file (chunks byte-for-byte, frames as images, timing as JSON) "
                            "until Ctrl-C, SIGTERM or --duration. An existing file is never "
                            "overwritten: FILE.1.mcap, ... is written instead. Exit status 1 "
                            "when no peer is reached or the file cannot be written.")
    add_out(p, "MCAP file to write", default=Path("minority.mcap"), metavar="FILE.mcap")
    p.add_argument("--run", default="*", help="record one run id only (*: every run)")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="stop after S seconds (0: run until stopped)")
    p.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="keep trying to reach the server for S seconds at start")
    p.add_argument("--compression", choices=["none", "lz4", "zstd"], default="none",
                   help="MCAP chunk compression (particle floats compress poorly)")
    p.add_argument("--flush-interval", type=float, default=0.5, metavar="S",
                   help="close an MCAP chunk at least every S seconds, so a killed recorder "
                        "loses at most that much")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    _add_network(p)
    p.set_defaults(func=_cmd_record)


def _cmd_record(args: argparse.Namespace) -> int:
    from mcap.writer import CompressionType

    from minority.protocol.log import Recorder, free_log_path
    from minority.protocol.session import Role, options_from_args

    opts = options_from_args(args)
    opts.connect_timeout_s = args.wait
    role = Role.SERVER if args.listen else Role.CLIENT  # --listen: sims may connect to us
    session = _open_peer(opts, role, "record", args.wait)
    if session is None:
        return FAILED
    try:
        out = free_log_path(parent_made(args.out))  # never overwrite a log
        recorder = Recorder(session, out, run=args.run,
                            compression=CompressionType[args.compression.upper()],
                            flush_interval_s=args.flush_interval)
    except OSError as exc:
        session.close()
        return fail("record", f"cannot write {args.out}: {exc}")
    stop = stop_on_signals()
    print(f"recording minority/{args.run}/** to {out} (Ctrl-C to stop)", file=sys.stderr)
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
        complete = recorder.close()
        session.close()
    print(f"\n{recorder.written} messages written to {out} "
          f"({recorder.writer.rejected} rejected as malformed, {recorder.dropped} dropped)",
          file=sys.stderr)
    if not complete:
        return fail("record", f"{out}: {recorder.writer.failure}; {recorder.writer.ending}; "
                              f"{recorder.write_errors} messages not written")
    return 0


# --- demo -------------------------------------------------------------------------------

def _demo_parser(sub) -> None:
    from dataclasses import fields

    from minority.demo import DemoOptions

    d = argparse.Namespace(**{f.name: f.default for f in fields(DemoOptions)})  # no checks yet
    p = command(sub, "demo", help="the whole pipeline on one machine, embedded defaults",
                description="Oracle rollout, spec, render server, 2-rank sim, frames, log, "
                            "report and score, on one machine. Exit status 2 on a bad "
                            "argument, 1 when a stage fails.")
    add_out(p, "where everything goes", default=d.out, metavar="DIR")
    p.add_argument("--ranks", type=int, default=d.ranks, help="MPI ranks of the sim")
    p.add_argument("--duration", type=float, default=d.duration_s, metavar="S",
                   help="simulated time, s (the runout ends near 0.62 s)")
    p.add_argument("--cell-size", type=float, default=d.cell_size_m, metavar="M",
                   help="grid cell, m: 0.016 gives 12,960 particles, 0.032 gives 1,800")
    p.add_argument("--frames", type=int, default=d.frames, help="frame budget, all views")
    p.add_argument("--threads", type=int, default=d.threads, help="threads per process")
    p.add_argument("--http", metavar="[HOST:]PORT",
                   help="watch the run in a browser: the render server's live view on this "
                        "address (0: a free port on 127.0.0.1; the URL is printed)")
    p.add_argument("--no-follow", action="store_true",
                   help="leave out the closed-loop oracle (default: minority oracle follow runs "
                        "beside the server and re-forecasts when the run leaves the "
                        "prediction; its spec updates in DIR/follow.log)")
    p.set_defaults(func=_cmd_demo, kernels=True)


def _cmd_demo(args: argparse.Namespace) -> int:
    from minority.demo import DemoOptions, main

    try:
        options = DemoOptions(out=args.out, ranks=args.ranks, duration_s=args.duration,
                              cell_size_m=args.cell_size, frames=args.frames,
                              threads=args.threads, http=args.http,
                              follow=not args.no_follow)
    except ValueError as exc:
        return fail("demo", exc, BAD_INPUT)
    try:
        return main(options)
    except (RuntimeError, ValueError, OSError, subprocess.TimeoutExpired) as exc:
        return fail("demo", exc)


# --- the command ------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    from minority import deploy_cli, log_cli, oracle_cli

    parser = argparse.ArgumentParser(
        prog="minority", formatter_class=HelpFormatter,
        description="In situ visualization of particle simulations, steered by a graph "
                    "network oracle. Units: metres, seconds, kilograms, pascals, degrees. "
                    "Exit status 2 for bad usage or input, 1 for a failure at run time.")
    parser.add_argument("--version", action="version", version=f"minority {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_serve_parser, _sim_parser, oracle_cli.add_parser, _replay_parser,
                _report_parser, _record_parser, log_cli.add_parser, deploy_cli.add_parser,
                _demo_parser):
        add(sub)
    return parser


def _own_parsers(parser: argparse.ArgumentParser) -> None:
    """Give every (sub)parser's namespace the parser that parsed it (the innermost wins)."""
    parser.set_defaults(_parser=parser)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _own_parsers(sub)


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("minority")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def drop_stale_numba_caches() -> None:
    """protocol.jitcache's housekeeping for every package with cached kernels (found without
    importing them)."""
    from importlib.util import find_spec

    from minority.protocol.jitcache import drop_stale_numba_cache

    for name in NUMBA_PACKAGES:
        for folder in find_spec(name).submodule_search_locations:
            drop_stale_numba_cache(folder)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    score = argv[:2] == ["report", "score"]
    parser = score_parser() if score else build_parser()
    _own_parsers(parser)
    args, extra = parser.parse_known_args(argv[2:] if score else argv)
    if extra:  # said by the subcommand's parser, with its usage (not the top level's)
        args._parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.argv = argv  # `minority sim --ranks N` re-runs itself under mpiexec
    if getattr(args, "kernels", False):
        drop_stale_numba_caches()  # numba does not track cross-file changes
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

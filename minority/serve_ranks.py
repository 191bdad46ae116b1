"""`minority serve` on N MPI ranks (under mpiexec or srun, or `--ranks N`): the wiring.

Start-up, in this order on every rank: two communicators (control messages, collective
rendering), the render kernels warmed up (numba compiles before any heartbeat counts), rank
0 opens its zenoh session (listening, as one process does), then the others theirs (clients
of rank 0, or of --connect), rank 0 starts the RenderServer with the Coordinator, and every
rank k > 0 runs its Worker loop (render_server.serve_mpi) until rank 0 stops it.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback

from minority.cliargs import BAD_INPUT, FAILED, parent_made


def end_line(servers) -> str:
    """What `serve --exit-when-done` says when every run has ended."""
    if any(server.failures() for server in servers):
        return "every run has ended, not all as it should (below)"
    return "every rank is done and the last step rendered"


def report_failures(servers) -> int:
    """Say on stderr what went wrong in each server's last run (a rank killed before its
    done event, a log cut short: RenderServer.failures); FAILED if anything did, else 0."""
    status = 0
    for server in servers:
        for failure in server.failures():
            print(f"minority serve: error: run {server.current.name}: {failure}",
                  file=sys.stderr, flush=True)
            status = FAILED
    return status


def serve_ranks(args: argparse.Namespace, spec, comm) -> int:
    """Rank 0: the server; ranks k > 0: workers. Returns the exit status (rank 0 exits with
    MPI_Abort after a rank died: MPI cannot finalize with it). An unexpected error on any
    rank ends the job (MPI_Abort), so no other rank waits for it in a barrier."""
    try:
        return _serve_ranks(args, spec, comm)
    except Exception:
        traceback.print_exc()
        print(f"minority serve: render rank {comm.Get_rank()} failed (above): ending every rank",
              file=sys.stderr, flush=True)
        comm.Abort(FAILED)
        return FAILED


def _serve_ranks(args: argparse.Namespace, spec, comm) -> int:
    import zenoh

    from minority.protocol.session import (
        DEFAULT_ENDPOINT,
        Role,
        open_session,
        options_from_args,
        shm_pool_for,
    )
    from minority.render_server.daemon import warm_up
    from minority.render_server.serve_mpi import warm_up_distributed, worker_network

    ctl, draw = comm.Dup(), comm.Dup()
    rank = comm.Get_rank()
    opts = options_from_args(args)
    opts.shm_pool_bytes = shm_pool_for(max((3 * v.width * v.height for v in spec.views),
                                           default=0) + 65536)
    warm_up()
    warm_up_distributed(draw)
    from mpi4py import MPI

    host = MPI.Get_processor_name()
    root_host = ctl.bcast(host, root=0)
    session = None
    if rank == 0:
        try:
            session = open_session(opts, Role.SERVER)
        except (zenoh.ZError, OSError) as exc:
            print(f"minority serve: cannot open the zenoh session: {exc}", file=sys.stderr)
            comm.Abort(FAILED)
    listening = opts.listen
    if not listening and opts.config is None:
        listening = [DEFAULT_ENDPOINT]
    elif not listening and rank == 0:
        listening = _config_listen(opts)
    listening = ctl.bcast(listening, root=0)
    unreachable = [] if opts.connect else [e for e in listening if e.rsplit(":", 1)[-1] == "0"]
    if unreachable and rank == 0:  # the others wait below until the abort ends them
        print(f"minority serve: error: the other render ranks connect to rank 0's listen "
              f"endpoints, and {', '.join(unreachable)} names no port: give --listen with "
              "a port (or --connect, where all ranks meet)", file=sys.stderr, flush=True)
        comm.Abort(BAD_INPUT)
    ctl.Barrier()  # rank 0 listens
    if rank > 0:
        wopts = worker_network(opts, listening, host == root_host, root_host)
        try:
            session = open_session(wopts, Role.CLIENT,
                                   configure=lambda cfg: cfg.insert_json5("listen/endpoints", "[]"))
        except (zenoh.ZError, OSError) as exc:
            print(f"minority serve: render rank {rank}: cannot reach rank 0's zenoh session at "
                  f"{', '.join(wopts.connect)}: {exc}", file=sys.stderr, flush=True)
            comm.Abort(FAILED)
    ctl.Barrier()  # every rank's session is open
    if rank > 0:
        return _worker(args, spec, ctl, draw, session)
    return _server(args, spec, ctl, draw, session)


def _config_listen(opts) -> list[str]:
    """The endpoints rank 0's session listens on by its --config file (none given by flag)."""
    import json

    from minority.protocol.session import Role, make_config

    cfg = make_config(opts, Role.SERVER)
    endpoints = json.loads(cfg.get_json("listen/endpoints")) or []
    if isinstance(endpoints, dict):  # zenoh's per-mode form: {"router": [...], "peer": [...]}
        endpoints = endpoints.get(json.loads(cfg.get_json("mode")) or "peer") or []
    return list(endpoints)


def _worker(args, spec, ctl, draw, session) -> int:
    from minority.render_server.serve_mpi import Worker, ignore_stop_signals

    ignore_stop_signals()
    worker = Worker(ctl, draw, session, spec.run, spec, args.max_sim_ranks, args.rank_timeout)
    print(f"render rank {ctl.rank}: pid {os.getpid()}, chunks of sim ranks "
          f"{ctl.rank}, {ctl.rank + ctl.size}, ...", file=sys.stderr, flush=True)
    ctl.Barrier()  # subscribed before rank 0 says it serves
    try:
        return worker.serve()
    finally:
        session.close()


def _server(args, spec, ctl, draw, session) -> int:
    from minority.render_server.daemon import RenderServer, ServerOptions
    from minority.render_server.serve_mpi import Coordinator
    from minority.signals import stop_on_signals

    live = None
    if args.http is not None:
        from minority.render_server.live import LiveView
        from minority.render_server.live_http import parse_address
        try:
            live = LiveView(args.out, *parse_address(args.http))
        except (ValueError, OSError) as exc:
            print(f"minority serve: error: --http {args.http}: {exc}", file=sys.stderr)
            ctl.Abort(BAD_INPUT)
        print(f"live view: {live.url}", file=sys.stderr, flush=True)
    coordinator = Coordinator(ctl, draw, spec.run, args.max_sim_ranks, args.rank_timeout)
    stop = stop_on_signals()
    ctl.Barrier()
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        record = None if args.no_record else (args.record or args.out / f"{spec.run}.mcap")
        if record is not None:
            parent_made(record)
        server = RenderServer(session, ServerOptions(
            spec, args.out, record, args.timeout, observer=live.observe if live else None,
            mpi=coordinator))
    except OSError as exc:
        print(f"minority serve: error: cannot start: {exc}", file=sys.stderr, flush=True)
        ctl.Abort(FAILED)
    coordinator.on_failure = server.abort
    coordinator.start()
    run = server.current
    print(f"serving run {spec.run!r} on {ctl.size} render ranks (rank 0: pid {os.getpid()}): "
          f"{len(spec.views)} views, "
          f"frames to {run.frames_dir}/" + (f", log {run.writer.path} (and its shards "
                                            f"{run.writer.path.stem}.render*.mcap)"
                                            if run.writer else ""),
          file=sys.stderr, flush=True)
    while not stop.wait(0.2) and not coordinator.aborted.is_set():
        if args.exit_when_done and server.finished.is_set():
            print(end_line([server]), file=sys.stderr)
            break
    if coordinator.aborted.is_set():
        print(f"minority serve: error: {coordinator.failure}; log closed: {server.summary()}",
              file=sys.stderr, flush=True)
        if live is not None:
            live.close()
        session.close()
        sys.stdout.flush()
        ctl.Abort(FAILED)  # ends every rank, a stuck one too (MPI cannot finalize without it)
    server.close()
    session.close()
    if live is not None:
        live.close()
    print(f"stopped: {server.summary()}", file=sys.stderr)
    return report_failures([server])

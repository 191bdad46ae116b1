"""`minority log ...`: argument parsing of the MCAP log tools (check, repair, export)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from minority.cliargs import add_out, command

REPAIRED_SUFFIX = ".repaired.mcap"


def default_output(log: Path) -> Path:
    """RUN.mcap -> RUN.repaired.mcap (any other name gets the suffix appended)."""
    return log.with_suffix(REPAIRED_SUFFIX) if log.suffix == ".mcap" else Path(f"{log}{REPAIRED_SUFFIX}")


def _readable(log: Path, command: str) -> bool:
    """Whether `log` is a file this process can open; if not, say why in one line."""
    if not log.is_file():
        why = "not a regular file" if log.exists() else "no such file"
        print(f"minority log {command}: error: {log}: {why}", file=sys.stderr)
        return False
    try:
        log.open("rb").close()
    except OSError as exc:
        print(f"minority log {command}: error: {exc}", file=sys.stderr)
        return False
    return True


def _stopped(result) -> str:
    return (f"{result.state.value} at byte {result.stopped_at:,} of {result.size:,} "
            f"({result.reason})")


def _cmd_check(args: argparse.Namespace) -> int:
    from minority.protocol.errors import ProtocolError
    from minority.protocol.repair import LogState, scan

    if not _readable(args.log, "check"):
        return 2
    try:
        result = scan(args.log)
    except ProtocolError as exc:
        print(f"minority log check: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"minority log check: error: {exc}", file=sys.stderr)
        return 1
    counts = (f"{result.messages} messages on {result.channels} channels, "
              f"{result.metadata} metadata, {result.attachments} attachments")
    if result.state is LogState.COMPLETE:
        print(f"{args.log}: complete: {counts}")
        return 0
    print(f"{args.log}: {_stopped(result)}: {counts} readable; "
          f"`minority log repair {args.log}` writes a complete copy of them")
    return 1


def _cmd_repair(args: argparse.Namespace) -> int:
    from minority.protocol.repair import LogState, repair

    out = args.out or default_output(args.log)
    if not _readable(args.log, "repair"):
        return 2
    if out.exists() and not args.force and not out.samefile(args.log):
        print(f"minority log repair: error: {out} exists (--force replaces it)", file=sys.stderr)
        return 2
    try:
        result = repair(args.log, out)
    except ValueError as exc:  # ProtocolError (not MCAP) or the output naming the input
        print(f"minority log repair: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"minority log repair: error: cannot write {out}: {exc}", file=sys.stderr)
        return 1
    source = "complete" if result.state is LogState.COMPLETE else _stopped(result)
    print(f"{args.log}: {source}; kept {result.messages} messages, {result.channels} channels, "
          f"{result.schemas} schemas, {result.metadata} metadata, {result.attachments} "
          f"attachments in {result.chunks} chunks -> {out}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from minority.protocol.errors import ProtocolError
    from minority.protocol.foxglove import export_foxglove

    if not _readable(args.log, "export"):
        return 2
    if args.out.exists() and not args.force:
        print(f"minority log export: error: {args.out} exists (--force replaces it)",
              file=sys.stderr)
        return 2
    if args.out.exists() and args.out.samefile(args.log):
        print(f"minority log export: error: {args.out} is the log itself", file=sys.stderr)
        return 2
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        result = export_foxglove(args.log, args.out, args.run)
    except ProtocolError as exc:
        print(f"minority log export: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"minority log export: error: cannot write {args.out}: {exc}", file=sys.stderr)
        return 1
    copied = ", ".join(f"{n} {topic}" for topic, n in result.copied.items()) or "no records"
    partial = f" ({result.partial_steps} without every rank's chunk)" if result.partial_steps else ""
    skipped = f"; {result.skipped} rejected payloads left out" if result.skipped else ""
    print(f"{args.log}: run {result.run}: {result.steps} point clouds{partial} with "
          f"{result.points:,} particles on /particles, {result.scenes} scene updates on /scene, "
          f"{copied}{skipped} -> {args.out}")
    return 0


def add_parser(sub) -> None:
    """Add `log` (with `check` and `repair`) to the subparsers `sub` of the minority command."""
    p = command(sub, "log", help="check or repair MCAP logs (e.g. of a killed server)",
                       description="Tools for the MCAP logs written by `minority serve`, "
                                   "`minority record` and `minority sim --record`. A log whose "
                                   "writer was killed has no footer: Foxglove, the `mcap` CLI "
                                   "and mcap's make_reader refuse it; `repair` writes a "
                                   "complete copy of its readable part.")
    lsub = p.add_subparsers(dest="log_command", required=True, metavar="ACTION")

    q = command(lsub, "check", help="say whether a log is complete, truncated or damaged",
                        description="Read a log front to back (chunk CRCs checked) and print "
                                    "one line: complete, truncated (its writer was killed: no "
                                    "footer) or damaged (an unreadable record inside it), with "
                                    "its readable message count. Exit status 0 when complete, "
                                    "1 when truncated or damaged (or unreadable), 2 on bad "
                                    "input (no such file, not MCAP).")
    q.add_argument("log", type=Path, metavar="IN.mcap", help="MCAP log to check")
    q.set_defaults(func=_cmd_check)

    q = command(lsub, "repair", help="write a complete copy of a cut-short or damaged log",
                        description="Copy every record of IN.mcap up to its first unreadable "
                                    "one (a cut-short tail or a damaged chunk) into a new, "
                                    "indexed MCAP file that Foxglove, the `mcap` CLI and "
                                    "make_reader open: same profile, schemas, channels and "
                                    "their metadata, messages (times, sequence and data "
                                    "unchanged), metadata and attachments, chunked and "
                                    "compressed as IN. A complete log is copied whole. Prints "
                                    "one line with the counts. The input is never modified; the "
                                    "output appears whole or not at all. Exit status 0 when "
                                    "written, 2 on bad input (no such file, not MCAP, output "
                                    "exists or is the input), 1 when the output cannot be "
                                    "written.")
    q.add_argument("log", type=Path, metavar="IN.mcap", help="MCAP log to repair")
    add_out(q, f"repaired copy (default: IN with suffix {REPAIRED_SUFFIX}); its directory "
               "is created", metavar="OUT.mcap")
    q.add_argument("--force", action="store_true", help="replace OUT.mcap if it exists")
    q.set_defaults(func=_cmd_repair)

    q = command(lsub, "export", help="write a copy of a run that Foxglove shows whole",
                        description="Write one run of IN.mcap to OUT.mcap for Foxglove (or "
                                    "Lichtblick): its particles as foxglove.PointCloud on "
                                    "/particles (one per step: x, y, z, every field as a "
                                    "colour channel, particle ids), its regions of interest "
                                    "and camera frusta as foxglove.SceneUpdate on /scene, and "
                                    "its frames (/frame/VIEW), /timing, /stats, /events and "
                                    "/spec unchanged. deploy/foxglove/minority.json is a "
                                    "layout for it. IN.mcap is not modified and stays the "
                                    "source for replay. Exit status 0 when written, 2 on bad "
                                    "input (no such file, not MCAP, several runs and no "
                                    "--run, OUT.mcap exists), 1 when OUT.mcap cannot be "
                                    "written.")
    q.add_argument("log", type=Path, metavar="IN.mcap", help="MCAP log to export")
    q.add_argument("--foxglove", action="store_true", required=True,
                   help="the format to write (the one there is): Foxglove's schemas, JSON")
    add_out(q, "the Foxglove file to write; its directory is created", metavar="OUT.mcap",
            required=True)
    q.add_argument("--run", help="the run to export (needed when IN.mcap holds several)")
    q.add_argument("--force", action="store_true", help="replace OUT.mcap if it exists")
    q.set_defaults(func=_cmd_export)

"""The live view's read-only window on the server's --out directory: the index of its runs
(frames, movies, reports, scores, logs) and the files themselves, never a path outside it.

A run directory is `{out}/{run}/` holding view directories of PNG frames (`{view}/*.png`,
written by the daemon), movies `{view}.mp4` and animated previews `{view}.webp` (`minority
replay --movie`, the demo), and `report.md` / `score.md` when present; beside it lie
`{out}/{run}.mcap` and the report's plots `{out}/{run}.timing.png`, `{out}/{run}.bytes.png`.
"""

from __future__ import annotations

import html
import os
import re
from pathlib import Path
from urllib.parse import quote, unquote

MAX_RUNS_LISTED = 500  # run directories in the index, newest first
MAX_DIR_ENTRIES = 10000  # entries of one directory listing
# what a file is served as; anything else downloads. HTML and SVG from --out are shown as
# text, never run as pages of this origin
CONTENT_TYPES = {".png": "image/png", ".mp4": "video/mp4", ".webp": "image/webp",
                 ".md": "text/plain; charset=utf-8", ".json": "application/json",
                 ".txt": "text/plain; charset=utf-8",
                 ".csv": "text/plain; charset=utf-8", ".html": "text/plain; charset=utf-8",
                 ".svg": "text/plain; charset=utf-8", ".mcap": "application/octet-stream"}
RUN_FILES = (".mp4", ".webp", ".md", ".json", ".png")  # shown in a run directory's row
BESIDE = (".mcap", ".timing.png", ".bytes.png")  # {out}/{run}{suffix}
RANGE_RE = re.compile(r"bytes=(\d*)-(\d*)")


def file_url(rel: str) -> str:
    """The URL path of a file under --out (`rel` relative, '/'-separated)."""
    return "/files/" + quote(rel)


def resolve_in(root: Path, rel: str) -> Path | None:
    """The existing path `rel` (URL-quoted, '/'-separated) names under `root`, or None when it
    does not exist or leaves `root` (through '..', an absolute path or a symlink)."""
    rel = unquote(rel)
    if "\x00" in rel or "\\" in rel:
        return None
    parts = [p for p in rel.split("/") if p not in ("", ".")]
    if ".." in parts:
        return None
    try:
        base = root.resolve()
        target = base.joinpath(*parts).resolve()
    except (OSError, RuntimeError):  # a symlink loop
        return None
    if target != base and not target.is_relative_to(base):
        return None
    return target if target.exists() else None


def content_type(path: Path) -> str:
    return CONTENT_TYPES.get(path.suffix.lower(), "application/octet-stream")


def byte_range(header: str | None, size: int) -> tuple[int, int] | None | str:
    """The [start, end) of a single `Range: bytes=a-b` header, None for the whole file, or
    "unsatisfiable" (status 416)."""
    if not header:
        return None
    m = RANGE_RE.fullmatch(header.strip())
    if m is None or m.group(1) == m.group(2) == "":
        return None  # several ranges or another unit: the whole file, as RFC 9110 allows
    if m.group(1) == "":  # the last N bytes
        n = int(m.group(2))
        return (max(size - n, 0), size) if n > 0 and size > 0 else "unsatisfiable"
    start = int(m.group(1))
    end = min(int(m.group(2)) + 1, size) if m.group(2) else size
    return (start, end) if start < size and start < end else "unsatisfiable"


def _views(run_dir: Path, rel: str) -> list[dict]:
    views = []
    for entry in sorted(os.scandir(run_dir), key=lambda e: e.name):
        if not entry.is_dir() or entry.name.startswith("."):
            continue
        frames = [e.name for e in os.scandir(entry.path) if e.name.endswith(".png")]
        movie = run_dir / f"{entry.name}.mp4"
        if not frames and not movie.is_file():
            continue
        views.append({"name": entry.name, "frames": len(frames),
                      "newest": file_url(f"{rel}/{entry.name}/{max(frames)}") if frames else None,
                      "dir": file_url(f"{rel}/{entry.name}/"),
                      "movie": file_url(f"{rel}/{movie.name}") if movie.is_file() else None})
    return views


def run_index(out_dir: Path) -> dict:
    """{"out", "files": top-level reports, "runs": [{name, views, files, modified_ns}]}, the
    runs newest first. A directory is a run when it holds frames, movies or a report."""
    out = Path(out_dir)
    result = {"out": str(out), "files": [], "runs": []}
    if not out.is_dir():
        return result
    runs = []
    for entry in os.scandir(out):
        if entry.is_file() and entry.name.endswith(".md"):
            result["files"].append({"name": entry.name, "url": file_url(entry.name)})
        if not entry.is_dir() or entry.name.startswith("."):
            continue
        run_dir = Path(entry.path)
        try:
            views = _views(run_dir, entry.name)
            files = sorted(e.name for e in os.scandir(run_dir)
                           if e.is_file() and e.name.endswith(RUN_FILES))
        except OSError:  # removed or unreadable meanwhile
            continue
        beside = [entry.name + s for s in BESIDE if (out / (entry.name + s)).is_file()]
        if not views and not files and not beside:
            continue
        runs.append({"name": entry.name, "views": views, "modified_ns": entry.stat().st_mtime_ns,
                     "files": [{"name": f, "url": file_url(f"{entry.name}/{f}")} for f in files]
                     + [{"name": f, "url": file_url(f)} for f in beside]})
    runs.sort(key=lambda r: (-r["modified_ns"], r["name"]))
    result["runs"] = runs[:MAX_RUNS_LISTED]
    result["files"].sort(key=lambda f: f["name"])
    return result


def directory_page(root: Path, target: Path) -> bytes:
    """An HTML listing of a directory under root (directories first, then files by name)."""
    rel = target.relative_to(root.resolve()).as_posix()
    prefix = "" if rel == "." else rel + "/"
    entries = sorted(os.scandir(target), key=lambda e: (not e.is_dir(), e.name))
    rows = []
    if prefix:
        parent = str(Path(rel).parent.as_posix())
        rows.append(f'<li><a href="{file_url("" if parent == "." else parent + "/")}">..</a></li>')
    for e in entries[:MAX_DIR_ENTRIES]:
        name = e.name + ("/" if e.is_dir() else "")
        rows.append(f'<li><a href="{html.escape(file_url(prefix + name))}">'
                    f"{html.escape(name)}</a></li>")
    more = len(entries) - MAX_DIR_ENTRIES
    if more > 0:
        rows.append(f"<li>... and {more} more</li>")
    title = html.escape(f"/{prefix}")
    return (f"<!doctype html><meta charset=utf-8><title>{title}</title>"
            f'<p><a href="/">live view</a></p><h1>{title}</h1><ul>{"".join(rows)}</ul>'
            ).encode()

"""Complete pictures under region culling, measured over the showcase run (the demo column,
12,960 particles, the oracle's spec): the same simulation three times on one rank,
recorded (no server; frames re-rendered from each record by the server's own code):

* `context`: the spec's regions, with the particles outside them sent once and again when
  they move more than the tolerance (the default);
* `regions`: the spec's regions only (`minority sim --no-context`; the baseline bytes);
* `full`: every particle at every due step (the spec without regions nor occlusion
  culling; the reference frames).

Prints JSON lines: per variant, the chunk bytes, chunks, rows and context rows (and rows
evicted) of the run, and its bytes against `regions`:
{"bench": "complete", "variant", "bytes", "chunks", "rows", "context_rows", "evicted",
 "bytes_vs_regions"}
and per view, the pixels of each `context` and `regions` frame that differ from the `full`
frame of the same step:
{"bench": "complete", "variant", "view", "frames", "frames_identical", "differing_px_max",
 "differing_px_mean"}

    python -m bench.complete [--spec SPEC.json] [--tolerance M ...] [--keep DIR] [--small]

Without --spec the oracle derives the demo's spec first (about 20 s). About 3 minutes, and
one more per extra tolerance. With --keep, records already in DIR are reused. --small: a
smoke test (1,800 particles, 0.15 s, 12 frames of 160x120; half a minute).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from minority.protocol import Chunk, keys
from minority.protocol.logread import read_log
from minority.protocol.spec import Spec
from minority.render_server.rerender import rerender

RUN = "demo"
KEYS = {"complete": ("variant", "bytes", "chunks", "rows", "context_rows", "evicted",
                     "bytes_vs_regions"),
        "complete view": ("variant", "view", "frames", "frames_identical", "differing_px_max",
                          "differing_px_mean")}
SMALL = {"duration_s": 0.15, "cell_size_m": 0.032, "frames": 12, "width": 160, "height": 120}


def demo_inputs(work: Path, spec: Path | None, small: bool = False) -> tuple[Path, Path]:
    """The demo's scene TOML and the oracle's spec (derived now unless given); small: at the
    SMALL size."""
    from minority.demo import DemoOptions, demo_column, run_oracle

    o = DemoOptions(out=work, **(SMALL if small else {}))
    scene = work / "scene.toml"
    scene.write_text(demo_column(o))
    if spec is None:
        spec, _ = run_oracle(o, scene, lambda line: print(line, file=sys.stderr, flush=True))
    return scene, spec


def without_regions(spec_path: Path, out: Path) -> Path:
    doc = json.loads(spec_path.read_text())
    for view in doc["views"]:
        view.pop("regions", None)
        view["occlusion_cull"] = False
        for window in view.get("schedule", []):
            window.pop("regions", None)
    out.write_text(json.dumps(doc))
    return out


def simulate(scene: Path, spec: Path, record: Path, extra: list[str]) -> None:
    if record.exists():
        print(f"reusing {record}", file=sys.stderr, flush=True)
        return
    cmd = [sys.executable, "-m", "minority", "sim", str(scene), "--spec", str(spec),
           "--run", RUN, "--record", str(record), "-o", str(record.with_suffix(".h5")),
           "--ranks", "1", "--threads", "1", "-q", *extra]
    print("+", " ".join(cmd[2:]), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True)


def chunk_totals(record: Path) -> dict:
    total = {"bytes": 0, "chunks": 0, "rows": 0, "context_rows": 0, "evicted": 0}
    for r in read_log(record, [keys.log_topic(RUN, keys.Topic.CHUNK)]):
        chunk: Chunk = r.decode()
        total["bytes"] += len(r.data)
        total["chunks"] += 1
        total["rows"] += chunk.count
        if chunk.context_ids is not None:
            total["context_rows"] += len(chunk.context_ids)
            total["evicted"] += len(chunk.evict_ids)
    return total


def differing_pixels(a: Path, b: Path) -> int:
    x, y = np.asarray(Image.open(a)), np.asarray(Image.open(b))
    return int(np.any(x != y, axis=-1).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spec", type=Path, help="the spec (default: the oracle's, derived now)")
    ap.add_argument("--tolerance", type=float, nargs="+", default=[None], metavar="M",
                    help="context tolerances to measure, m (default: the sim's)")
    ap.add_argument("--keep", type=Path, help="work in this directory and keep it")
    ap.add_argument("--small", action="store_true",
                    help="a smoke test: 1,800 particles, 0.15 s, 12 frames of 160x120")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        scene, spec_path = demo_inputs(work, args.spec, args.small)
        full_spec = without_regions(spec_path, work / "spec_full.json")
        variants = {"regions": (spec_path, ["--no-context"]),
                    "full": (full_spec, ["--no-context"])}
        for tol in args.tolerance:
            name = "context" if tol is None else f"context_{tol:g}"
            variants[name] = (spec_path, [] if tol is None else ["--context-tolerance", str(tol)])
        for name, (spec, extra) in variants.items():
            simulate(scene, spec, work / f"{name}.mcap", extra)
            if not (work / name).exists():
                rerender(work / f"{name}.mcap", Spec.load(spec), work / name)
        base = chunk_totals(work / "regions.mcap")
        for name in variants:
            t = chunk_totals(work / f"{name}.mcap")
            print(json.dumps({"bench": "complete", "variant": name, **t,
                              "bytes_vs_regions": round(t["bytes"] / base["bytes"], 4)}))
        for name in [v for v in variants if v != "full"]:
            for view_dir in sorted((work / "full").iterdir()):
                diffs = [differing_pixels(f, work / name / view_dir.name / f.name)
                         for f in sorted(view_dir.glob("*.png"))
                         if (work / name / view_dir.name / f.name).exists()]
                print(json.dumps({"bench": "complete", "variant": name, "view": view_dir.name,
                                  "frames": len(diffs),
                                  "frames_identical": sum(d == 0 for d in diffs),
                                  "differing_px_max": max(diffs, default=0),
                                  "differing_px_mean": round(float(np.mean(diffs)), 1)
                                  if diffs else 0.0}))


if __name__ == "__main__":
    main()

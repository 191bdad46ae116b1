"""Error against run time of the oracles that predict one target run.

Target: the full MPM run of a scene (default column_13k, the showcase). Oracles: GNS
checkpoints (model size, message-passing depth) rolled out on the scene at their particle
spacing from the MPM's first frames, as `minority oracle rollout` does (run time includes
that warm start), and the MPM itself on the same column at coarser grids. Each is scored by the
relative error of runout, final height and displacement range (gns/metrics.py) against the
target, and by when it predicts the peak of the motion and the return to rest
(gns/events.py: kinetic-energy peak, and back below 1 % of it), the event times the oracle
schedules by. Prints a JSON line per oracle:
{"bench": "surrogate", "oracle": .., "particles": N, "run_s": .., "runout_error": ..,
 "height_error": .., "displacement_range_error": .., "peak_s": .., "rest_s": ..}
Rows "target coarse-grained by 2 (mean|sample)" score the target run itself made one particle
per 2x2x2 group, as the GNS training data are (gns.dataset.coarse_grain: the group's mean, or
one sampled member): the error of a model exact on data coarse-grained that way.
Also writes OUT/surrogate.md (table) and OUT/surrogate.png (error against run time).
MPM runs go to OUT/ and are reused when complete.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from minority.gns.dataset import COARSE_GRAIN_METHODS, coarse_grain
from minority.gns.events import find_events
from minority.gns.metrics import deposit, relative_errors
from minority.gns.runtime import tune_allocator
from minority.gns.train import load_checkpoint
from minority.sim.scene import load_scene, scene_path
from minority.warmstart import predict_scene

# coarse grids of the column_13k geometry: (cell m, particles per cell per axis); the domain is
# rounded up to whole cells (the column and channel width are unchanged)
COARSE = [(0.048, 2), (0.036, 2), (0.024, 2), (0.016, 1)]
CG_FACTOR = 2  # the GNS data's coarse_grain (gns/configs/column_sweep_cg2.toml)
KEYS = {"surrogate": ("oracle", "particles", "run_s", "runout_error", "height_error",
                      "displacement_range_error", "peak_s", "rest_s")}


def coarse_scene(text: str, cell: float, ppc: int, size) -> str:
    size = [float(np.ceil(s / cell - 1e-9) * cell) for s in size]
    text = re.sub(r"(?m)^size_m = .*$", f"size_m = [{size[0]!r}, {size[1]!r}, {size[2]!r}]", text)
    text = re.sub(r"(?m)^cell_size_m = .*$", f"cell_size_m = {cell!r}", text)
    return re.sub(r"(?m)^per_cell_per_axis = .*$", f"per_cell_per_axis = {ppc}", text)


def run_mpm(scene: Path, out: Path, threads: int) -> float:
    """Run `minority sim` unless out is complete; wall seconds of the run (from the file)."""
    if out.exists():
        with h5py.File(out, "r") as f:
            if "wall_s" in f.attrs:
                return float(f.attrs["wall_s"])
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "minority", "sim", str(scene), "--out", str(out),
                    "--threads", str(threads), "--no-publish", "-q"], check=True)
    wall = time.perf_counter() - t0
    with h5py.File(out, "a") as f:
        f.attrs["wall_s"] = wall
    return wall


def positions(path: Path) -> np.ndarray:
    with h5py.File(path, "r") as f:
        return f["positions"][: len(f["time"])]


def event_times(path: Path | None = None, pos: np.ndarray | None = None,
                frame_interval_s: float | None = None) -> dict:
    """peak_s and rest_s (s) of an MPM run's HDF5 (path) or of a trajectory (pos, interval)."""
    if path is not None:
        with h5py.File(path, "r") as f:
            t = f["time"][:]
        pos, frame_interval_s = positions(path), float(t[1] - t[0])
    ev = find_events(pos, frame_interval_s)
    return {"peak_s": ev.peak_s, "rest_s": ev.runout_end_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="*", type=Path, help="GNS checkpoints")
    ap.add_argument("--scene", default="column_13k")
    ap.add_argument("--out", type=Path, default=Path("data/surrogate"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-mpm", action="store_true", help="skip the coarse MPM oracles")
    ap.add_argument("--start", choices=("mpm", "rest"), default="mpm",
                    help="GNS first frames: from the MPM (the oracle's default) or at rest")
    args = ap.parse_args()
    missing = [str(c) for c in args.checkpoints if not c.is_file()]
    if missing:  # before the target run, not after its minutes
        ap.error(f"no such checkpoint: {', '.join(missing)}")
    tune_allocator()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    path = scene_path(args.scene)
    scene = load_scene(path)
    target_h5 = args.out / f"{scene.name}_target.h5"
    target_s = run_mpm(path, target_h5, args.threads)
    target = positions(target_h5)  # [frames, n, 3] m, read once
    ref = deposit(target)
    rows = [{"oracle": f"target MPM dx={scene.cell_size_m}", "particles": target.shape[1],
             "run_s": target_s, **{f"{k}_error": 0.0 for k in (
                 "runout", "height", "displacement_range")}, **event_times(target_h5)}]
    with h5py.File(target_h5, "r") as f:
        interval = float(f["time"][1] - f["time"][0])
    for method in COARSE_GRAIN_METHODS:
        cg = coarse_grain(target, scene.particle_spacing_m, CG_FACTOR, method)
        rows.append({"oracle": f"target coarse-grained by {CG_FACTOR} ({method})",
                     "particles": cg.shape[1], "run_s": target_s,
                     **{f"{k}_error": v for k, v in relative_errors(deposit(cg), ref).items()},
                     **event_times(pos=cg, frame_interval_s=interval)})
    if not args.no_mpm:
        text = path.read_text()
        for cell, ppc in COARSE:
            p = args.out / f"{scene.name}_dx{cell}_ppc{ppc}.toml"
            p.write_text(coarse_scene(text, cell, ppc, scene.size_m))
            h5 = p.with_suffix(".h5")
            wall = run_mpm(p, h5, args.threads)
            pos = positions(h5)
            err = relative_errors(deposit(pos), ref)
            rows.append({"oracle": f"MPM dx={cell} ppc={ppc}", "particles": pos.shape[1],
                         "run_s": wall, **{f"{k}_error": v for k, v in err.items()},
                         **event_times(h5)})
    for ck in args.checkpoints:  # the oracle's own path: `minority oracle rollout --start`
        t0 = time.perf_counter()
        pred = predict_scene(ck, path, start=args.start, log=sys.stderr)
        wall = time.perf_counter() - t0  # with the MPM warm start
        err = relative_errors(deposit(pred.positions), ref)
        _, meta = load_checkpoint(ck)
        c = meta["model_config"]
        rows.append({"oracle": f"GNS {Path(ck).stem} L{c['latent']} M{c['message_passing']} "
                               f"step {meta['step']}"
                     f"{'' if args.start == 'mpm' else ' from rest'}",
                     "particles": pred.positions.shape[1], "run_s": wall,
                     **{f"{k}_error": v for k, v in err.items()},
                     **event_times(pos=pred.positions, frame_interval_s=pred.frame_interval_s)})
    for r in rows:
        print(json.dumps({"bench": "surrogate", **{k: round(v, 4) if isinstance(v, float) else v
                                                   for k, v in r.items()}}), flush=True)
    write_table(rows, args.out / "surrogate.md")
    write_plot(rows, args.out / "surrogate.png")


def write_table(rows: list[dict], path: Path) -> None:
    lines = ["| oracle | particles | run time (s) | runout error | height error | "
             "displacement range error | peak (s) | at rest (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['oracle']} | {r['particles']} | {r['run_s']:.1f} | "
              f"{100 * r['runout_error']:.1f}% | {100 * r['height_error']:.1f}% | "
              f"{100 * r['displacement_range_error']:.1f}% | {r['peak_s']:.3f} | "
              f"{r['rest_s']:.3f} |" for r in rows]
    path.write_text("\n".join(lines) + "\n")


def write_plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for r in rows[1:]:
        err = max(r["runout_error"], r["displacement_range_error"])
        marker = "o" if r["oracle"].startswith("GNS") else "s"
        ax.scatter(r["run_s"], 100 * err, marker=marker)
        ax.annotate(r["oracle"], (r["run_s"], 100 * err), fontsize=7, xytext=(4, 3),
                    textcoords="offset points")
    ax.axvline(rows[0]["run_s"], ls="--", c="gray", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("run time on this machine (s); dashed: the target MPM run")
    ax.set_ylabel("max(runout, displacement range) error (%)")
    ax.set_title(rows[0]["oracle"].replace("target ", "target: "))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()

"""Calibration of the ensemble oracle on the held-out scenes: do the actual events and deposit
fall inside the intervals the spec states, and what the widening costs in frames and bytes.

Scenes: the test split of gns/configs/column_sweep_cg2.toml, the data the shipped checkpoint
was made for (test_000..test_003 in the held-out bands, and the showcase column; wide_10x is
left out by default: its MPM run and its 15k-particle rollouts take many minutes each). Each
scene's MPM run is made at the data's resolution (twice the model's, as `minority oracle
dataset` runs it; tens of seconds each on one core) unless RUNS already holds it; the GNS
starts from the run's own first frames coarse-grained as the dataset is (as `minority oracle
evaluate` does) and each perturbation's members are rolled out once and kept in OUT.

Per scene, perturbation ("jitter" and "friction" with --members K each, "both": those 2K - 1
members together; gns.ensemble) and widening factor it prints a JSON line:
{"bench": "oracle_calibration", "scene", "perturb", "members", "widen",
 "events": {name: {"actual_s", "nominal_s", "interval_s", "inside"}},
 "deposit": {measure: {"actual_m", "nominal_m", "band_m", "inside"}},
 "frames": {"single", "ensemble", "single_in_critical", "ensemble_in_critical"},
 "bytes": {"single", "ensemble", "ratio"}, "rollout_s": mean s per member}
and then one summary line per (perturbation, widen) with the coverage over the scenes:
{"bench": "oracle_calibration_summary", "perturb", "widen", "scenes", "events_inside",
 "events", "deposit_inside", "deposits", "bytes_ratio", "frames_in_critical_ratio"}

Actual: the full MPM run (every particle, every 5 ms): its events by the oracle's own rules
(gns.events) and its deposit (gns.metrics.deposit). Frames and bytes: the spec's
`request` stepped over the run's output frames (2.5 ms apart): a view due at a frame is a
frame rendered; bytes are 24 B (position and displacement, float32) per run particle inside
the due regions (no occlusion culling, no context rows: the regions' share alone).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from minority.gns.dataset import read_sim_trajectory
from minority.gns.ensemble import EnsembleOptions, perturbed_starts, roll_members
from minority.gns.events import event_times, fast_windows, find_events
from minority.gns.metrics import deposit
from minority.gns.oracle import Oracle, OracleOptions
from minority.gns.runtime import tune_allocator
from minority.gns.sweep import load_config, plan
from minority.gns.train import load_checkpoint
from minority.protocol.spec import inside_mask
from minority.protocol.trajectory import read_sim
from minority.sweep import complete, run_scene, scene_toml

CONFIG = Path("gns/configs/column_sweep_cg2.toml")
CHECKPOINT = Path("gns/checkpoints/column_l64_m5.pt")
BYTES_PER_PARTICLE = 24  # position and displacement, float32 x 3 each
MEASURES = ("runout_m", "height_m", "displacement_max_m")
KEYS = {"oracle_calibration": ("scene", "perturb", "members", "widen", "events", "deposit",
                               "frames", "bytes", "rollout_s"),
        "oracle_calibration_summary": ("perturb", "widen", "scenes", "events_inside", "events",
                                       "deposit_inside", "deposits", "bytes_ratio",
                                       "frames_in_critical_ratio")}


def make_runs(cfg, runs: Path, scenes: list[str] | None, threads: int) -> list:
    """The test split's plans (default: all but wide_10x), their MPM runs made if missing."""
    runs.mkdir(parents=True, exist_ok=True)
    plans = [p for p in plan(cfg) if p.split == "test"
             and (p.name in scenes if scenes else p.name != "wide_10x")]
    for p in plans:
        toml, h5 = runs / f"{p.name}.toml", runs / f"{p.name}.h5"
        if not complete(h5, cfg):
            toml.write_text(scene_toml(cfg, p))
            t0 = time.perf_counter()
            run_scene(toml, h5, threads)
            print(f"calibration: MPM run {p.name} ({p.particles * cfg.coarse_grain ** 3} "
                  f"particles) {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return plans


def members_of(model, h5: Path, cfg, k: int, out: Path) -> tuple[dict, float]:
    """The ensembles of the scene run h5 ({perturbation: trajectories [frames, n, 3] m, the
    nominal first}) and the mean wall s per member rollout. One rollout set serves all three:
    "both" with 2(k - 1) + 1 members is "jitter" and "friction" with k each (gns.ensemble).
    Kept in out/{scene}_k{k}.npz."""
    cache = out / f"{h5.stem}_k{k}.npz"
    if cache.exists():
        z = np.load(cache)
        trajs, wall = list(z["members"]), float(z["wall_s"])
    else:
        pos, attrs = read_sim_trajectory(h5, cfg.stride, cfg.coarse_grain,
                                         cfg.coarse_grain_method)
        c1 = model.config.input_velocities + 1
        starts = perturbed_starts(pos[:c1], attrs["friction_angle_deg"],
                                  float(attrs["particle_spacing_m"]),
                                  EnsembleOptions(members=2 * (k - 1) + 1, perturb="both"))
        trajs, labels = roll_members(model, starts, np.asarray(attrs["bounds_m"]),
                                     len(pos) - c1, log=sys.stderr)
        if len(trajs) < len(starts):
            raise RuntimeError(f"{h5.stem}: {len(starts) - len(trajs)} members diverged")
        wall = float(np.mean([m["wall_s"] for m in labels]))
        np.savez(cache, members=np.stack(trajs), wall_s=wall)
    return {"jitter": trajs[:1] + trajs[1::2], "friction": trajs[:1] + trajs[2::2],
            "both": trajs}, wall


def actual(h5: Path, stride: int) -> dict:
    """The full run's events (s, every `stride`-th output frame), deposit (m), positions
    [frames, n, 3] at every output frame and their times (s)."""
    full, attrs = read_sim(h5, 1)
    dt = float(attrs["output_interval_s"])
    ev = find_events(full[::stride], dt * stride)
    d = deposit(full)
    return {"events": event_times(ev, dt * stride), "positions": full,
            "time_s": np.arange(len(full)) * dt,
            "critical": fast_windows(np.arange(len(ev.speed_scale_m_s)) * dt * stride,
                                     ev.speed_scale_m_s),
            "deposit": {"runout_m": d.runout_m, "height_m": d.height_m,
                        "displacement_max_m": d.displacement_max_m}}


def cost(spec, run: dict) -> dict:
    """Frames and bytes of the spec stepped over the run's output frames (module docstring)."""
    frames = in_critical = sent = 0
    t, x = run["time_s"], run["positions"]
    for k in range(len(t)):
        req = spec.request(k, float(t[k]), float(t[k - 1]) if k else None)
        if req is None:
            continue
        frames += len(req.views)
        in_critical += len(req.views) * any(a <= t[k] <= b for a, b in run["critical"])
        n = x.shape[1] if req.regions is None else int(inside_mask(x[k], req.regions).sum())
        sent += n * BYTES_PER_PARTICLE
    return {"frames": frames, "in_critical": in_critical, "bytes": sent}


def main() -> None:
    ap = argparse.ArgumentParser(
        description="Calibration of the ensemble oracle on the held-out scenes: a JSON line "
                    "per scene, perturbation and widening (whether the run's events and "
                    "deposit fell inside, frames and bytes against the single rollout), then "
                    "a summary line per perturbation and widening. Module docstring: what "
                    "each field means.")
    ap.add_argument("--checkpoint", type=Path, default=CHECKPOINT,
                    help=f"GNS checkpoint (default: {CHECKPOINT})")
    ap.add_argument("--runs", type=Path, default=Path("data/calibration/runs"),
                    help="MPM runs of the test scenes (made when missing)")
    ap.add_argument("--out", type=Path, default=Path("data/calibration"),
                    help="the members' rollouts, kept")
    ap.add_argument("--scene", action="append", help="only this scene (repeatable)")
    ap.add_argument("--members", type=int, default=5,
                    help="K of the jitter and friction ensembles, the nominal included ("
                         "both: their 2K - 1 members together)")
    ap.add_argument("--perturb", nargs="+", default=["jitter", "friction", "both"],
                    choices=["jitter", "friction", "both"],
                    help="the ensembles to score (default: all three)")
    ap.add_argument("--widen", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0],
                    help="interval widening factors to score (gns.ensemble.band)")
    ap.add_argument("--frames", type=int, default=120, help="the specs' frame budget")
    ap.add_argument("--threads", type=int, default=1, help="torch and numba threads")
    ap.add_argument("--config", type=Path, default=CONFIG,
                    help=f"the sweep config whose test split is scored (default: {CONFIG}, "
                         "the checkpoint's data)")
    args = ap.parse_args()
    tune_allocator()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    args.out.mkdir(parents=True, exist_ok=True)
    plans = make_runs(cfg, args.runs, args.scene, args.threads)
    model, ckpt = load_checkpoint(args.checkpoint)
    dt = float(ckpt["stats"]["frame_interval_s"])
    spacing = float(ckpt["stats"]["particle_spacing_m"])
    rows = []
    for p in plans:
        h5 = args.runs / f"{p.name}.h5"
        run = actual(h5, cfg.stride)
        bounds = np.asarray(read_sim(h5, len(run["time_s"]))[1]["bounds_m"])  # one frame read
        ensembles, wall = members_of(model, h5, cfg, args.members, args.out)
        nominal = ensembles["both"][0]
        single = cost(Oracle(nominal, dt, bounds, spacing,
                             OracleOptions(frames=args.frames)).spec(), run)
        for perturb in args.perturb:
            trajs = ensembles[perturb]
            for widen in args.widen:
                opts = OracleOptions(frames=args.frames, interval_widen=widen)
                oracle = Oracle(trajs[0], dt, bounds, spacing, opts, members=trajs[1:])
                spec = oracle.spec()
                ens = cost(spec, run)
                events = {e.name: {"actual_s": run["events"][e.name], "nominal_s": e.time_s,
                                   "interval_s": list(e.interval_s),
                                   "inside": e.earliest_s <= run["events"][e.name] <= e.latest_s}
                          for e in spec.events}
                dep = {m: {"actual_m": run["deposit"][m],
                           "nominal_m": getattr(spec.deposit, m).members[0],
                           "band_m": [getattr(spec.deposit, m).low, getattr(spec.deposit, m).high],
                           "inside": getattr(spec.deposit, m).low <= run["deposit"][m]
                           <= getattr(spec.deposit, m).high} for m in MEASURES}
                row = {"bench": "oracle_calibration", "scene": p.name, "perturb": perturb,
                       "members": len(trajs), "widen": widen, "events": events,
                       "deposit": dep,
                       "frames": {"single": single["frames"], "ensemble": ens["frames"],
                                  "single_in_critical": single["in_critical"],
                                  "ensemble_in_critical": ens["in_critical"]},
                       "bytes": {"single": single["bytes"], "ensemble": ens["bytes"],
                                 "ratio": ens["bytes"] / single["bytes"]},
                       "rollout_s": wall}
                rows.append(row)
                print(json.dumps(row), flush=True)
    for perturb in args.perturb:
        for widen in args.widen:
            sel = [r for r in rows if r["perturb"] == perturb and r["widen"] == widen]
            ev = [e["inside"] for r in sel for e in r["events"].values()]
            dp = [d["inside"] for r in sel for d in r["deposit"].values()]
            print(json.dumps({
                "bench": "oracle_calibration_summary", "perturb": perturb, "widen": widen,
                "scenes": len(sel), "events_inside": sum(ev), "events": len(ev),
                "deposit_inside": sum(dp), "deposits": len(dp),
                "bytes_ratio": float(np.mean([r["bytes"]["ratio"] for r in sel])),
                "frames_in_critical_ratio": float(np.mean(
                    [r["frames"]["ensemble_in_critical"] / max(r["frames"]["single_in_critical"], 1)
                     for r in sel]))}), flush=True)


if __name__ == "__main__":
    main()

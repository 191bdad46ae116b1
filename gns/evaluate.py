"""Accuracy of a checkpoint on the held-out scenes of a dataset: GNS rollout vs MPM."""

from __future__ import annotations

import sys
import time

import numpy as np

from minority.gns.dataset import load_metadata, load_split
from minority.gns.metrics import Deposit, deposit, mean_position_error, relative_errors
from minority.gns.rollout import RolloutError, rollout


def evaluate(model, dataset, split: str = "test", *, device: str = "cpu",
             names: list[str] | None = None, log=None) -> list[dict]:
    """One row per scene: deposit measures of both, relative errors, mean position error (m)
    over the predicted frames (not the C+1 MPM frames it starts from), rollout wall time (s).
    The rollout starts from the scene's first C+1 MPM frames and runs to its last frame.
    Scenes of a coarse-grained dataset are also scored against their MPM run at its own
    resolution (mpm_full, relative_error_full): the run the model is the oracle of."""
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    c1 = model.config.input_velocities + 1
    meta = load_metadata(dataset)
    full = {sc["name"]: Deposit(**sc["mpm_deposit"]) for sc in meta["scenes"]
            if "mpm_deposit" in sc} if int(meta.get("coarse_grain", 1)) > 1 else {}
    rows = []
    for traj in load_split(dataset, split):
        if names and traj.name not in names:
            continue
        frames = traj.positions.shape[0] - c1
        t0 = time.perf_counter()
        try:
            pred, _ = rollout(model, traj.positions[:c1].astype(np.float64),
                              traj.friction_angle_deg, traj.bounds_m, frames, device=device)
        except RolloutError as exc:
            rows.append({"scene": traj.name, "particles": traj.positions.shape[1],
                         "error": str(exc)})
            print(f"evaluate: {traj.name}: {exc}", file=log, flush=True)
            continue
        wall = time.perf_counter() - t0
        ref_dep, gns_dep = deposit(traj.positions), deposit(pred)
        row = {"scene": traj.name, "particles": traj.positions.shape[1], "frames": frames,
               "friction_angle_deg": traj.friction_angle_deg, "rollout_s": round(wall, 3),
               "mpm": ref_dep.as_dict(), "gns": gns_dep.as_dict(),
               "relative_error": relative_errors(gns_dep, ref_dep),
               "mean_position_error_m": mean_position_error(pred[c1:], traj.positions[c1:])}
        if traj.name in full:
            row["mpm_full"] = full[traj.name].as_dict()
            row["relative_error_full"] = relative_errors(gns_dep, full[traj.name])
        rows.append(row)
        e = row["relative_error"]
        print(f"evaluate: {traj.name} ({row['particles']} particles): runout "
              f"{gns_dep.runout_m:.3f} vs {ref_dep.runout_m:.3f} m ({100 * e['runout']:.1f}%), "
              f"height {100 * e['height']:.1f}%, displacement range "
              f"{100 * e['displacement_range']:.1f}%, mean position error "
              f"{row['mean_position_error_m'] * 1000:.1f} mm, {wall:.1f} s"
              + (f"; against the run at its resolution: runout "
                 f"{100 * row['relative_error_full']['runout']:.1f}%, displacement range "
                 f"{100 * row['relative_error_full']['displacement_range']:.1f}%"
                 if traj.name in full else ""), file=log, flush=True)
    return rows

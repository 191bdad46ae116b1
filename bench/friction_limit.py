"""A column near its friction limit: does the MPM's answer hold when the time step, the grid
or the velocity transfer change? One JSON line per case:

{"bench": "friction_limit", "case", "friction_deg", "cell_size_m", "cfl", "flip",
 "particles", "peak_s", "peak_speed_m_s", "fast_from_s", "max_displacement_m", "wall_s"}

The cases are bench.oracle_loop's columns (test_003 of gns/configs/column_sweep_cg2.toml:
0.192 m long, 0.144 m high, 0.128 m wide, 1 s) as the sweep runs them (cell 0.016 m, CFL
0.3, FLIP 0.99), each again at CFL 0.1: friction 20, 35.5 (test_003), 40 and 45 deg;
friction 45 also at CFL 0.25 and 0.2, with pure APIC (flip 0), and on a cell of 0.008 m
(8x the particles, `--fine`: about 2.5 min, and 7 min more at CFL 0.1; the rest takes
about 4 min on 2 cores). peak_s, peak_speed_m_s: the frame where the speed scale (the 95th
percentile of the particle speeds, as the ranks' Stats read it) is largest; fast_from_s:
where it first reaches half of that peak (the score's runout start; null when the peak is
the first settling's, within 0.05 s); max_displacement_m: at the run's end. A case whose
peak or displacement moves with the time step is not converged there.

    python -m bench.friction_limit [--fine] [--threads N] [--out DIR] [--cases CASE ...]
                                   [--config SWEEP.toml]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.oracle_loop import CONFIG

SETTLING_S = 0.05  # a peak before this is the first elastic settling, not a failure
KEYS = {"friction_limit": ("case", "friction_deg", "cell_size_m", "cfl", "flip", "particles",
                           "peak_s", "peak_speed_m_s", "fast_from_s?", "max_displacement_m",
                           "wall_s")}


def cases(fine: bool) -> list[tuple[str, dict]]:
    """(case name, ColumnSpec overrides) in run order."""
    out = []
    for deg, name in ((20.0, "friction_20"), (None, "test_003"), (40.0, "friction_40"),
                      (45.0, "friction_45")):
        for cfl in (0.3, 0.25, 0.2, 0.1) if deg == 45.0 else (0.3, 0.1):
            over = {"cfl": cfl} | ({} if deg is None else {"friction_angle_deg": deg})
            out.append((f"{name}_cfl{cfl}", over))
    out.append(("friction_45_pic", {"friction_angle_deg": 45.0, "flip": 0.0}))
    if fine:
        for cfl in (0.3, 0.1):
            out.append((f"friction_45_fine_cfl{cfl}",
                        {"friction_angle_deg": 45.0, "cell_size_m": 0.008, "cfl": cfl}))
    return out


def measure(h5: Path) -> dict:
    """The run's peak, fast phase and final displacement (see the module doc)."""
    import h5py

    from minority.gns.events import fast_windows
    from minority.protocol.flow import SPEED_QUANTILE

    with h5py.File(h5, "r") as f:
        t = f["time"][:]
        scale = np.quantile(np.linalg.norm(f["velocities"][:], axis=2), SPEED_QUANTILE, axis=1)
        disp = float(np.linalg.norm(f["displacements"][-1], axis=1).max())
        particles = int(f["positions"].shape[1])
    k = int(np.argmax(scale))
    fast = [w for w in fast_windows(t, scale) if w[0] <= t[k] <= w[1]]
    failed = t[k] > SETTLING_S
    return {"particles": particles, "peak_s": float(t[k]), "peak_speed_m_s": float(scale[k]),
            "fast_from_s": fast[0][0] if fast and failed else None,
            "max_displacement_m": disp}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.friction_limit", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fine", action="store_true",
                    help="also friction 45 deg on a 0.008 m cell at CFL 0.3 and 0.1 (~10 min)")
    ap.add_argument("--threads", type=int, default=2, help="numba threads (default 2)")
    ap.add_argument("--out", type=Path, default=Path("data/friction_limit"),
                    help="where the scenes and runs go")
    ap.add_argument("--cases", nargs="+", metavar="CASE",
                    help="only these cases (default: all; names as the lines print them)")
    ap.add_argument("--config", type=Path, default=CONFIG,
                    help="the sweep config of test_003 (default: gns/configs/"
                         "column_sweep_cg2.toml)")
    args = ap.parse_args(argv)
    from bench.oracle_loop import scene_plans
    from minority.sim.columns import channel_column_toml
    from minority.sweep import column, run_scene

    cfg, (base,) = scene_plans(["test_003"], args.config)
    chosen = cases(True)
    unknown = set(args.cases or []) - {name for name, _ in chosen}
    if unknown:
        ap.error(f"--cases: unknown {sorted(unknown)} (known: "
                 f"{', '.join(name for name, _ in chosen)})")
    chosen = [(n, o) for n, o in chosen if n in args.cases] if args.cases else cases(args.fine)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, over in chosen:
        c = replace(column(cfg, base), **over)
        scene = args.out / f"{name}.toml"
        scene.write_text(channel_column_toml(c, name))
        print(f"friction_limit: {name} ...", file=sys.stderr, flush=True)
        start = time.perf_counter()
        run_scene(scene, args.out / f"{name}.h5", args.threads)
        row = {"bench": "friction_limit", "case": name, "friction_deg": c.friction_angle_deg,
               "cell_size_m": c.cell_size_m, "cfl": c.cfl, "flip": c.flip,
               **measure(args.out / f"{name}.h5"),
               "wall_s": round(time.perf_counter() - start, 1)}
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""GNS inference benchmark: seconds per rollout step of the graph network.

Prints one JSON object per (particles, latent, message passing):
{"bench": "gns", "particles": N, "latent": L, "message_passing": M, "edges": E,
 "s_per_step": .., "graph_s_per_step": .., "threads": torch's}
s_per_step: one rollout step (radius graph + model + update), median of REPEAT steps after
one warm-up; graph_s_per_step: the radius-graph part of it. Particles sit on a jittered
lattice of spacing 0.016 m with connectivity radius 0.029 m (about 20-26 neighbours each),
as in the shipped dataset; weights are random (the cost does not depend on them).
The issue's reference (geoelements/gns on this machine, latent 128, M = 10): 0.32, 3.1, 16 s
per step at about 1k, 4k, 15k particles as installed, 0.31, 1.4, 5.5 s with its allocator tuned.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import torch

from minority.gns.graph import radius_graph
from minority.gns.model import GNS, ModelConfig
from minority.gns.runtime import tune_allocator

SPACING_M, RADIUS_M = 0.016, 0.029
LATTICES = {1_000: (10, 10, 10), 4_000: (16, 16, 16), 15_000: (25, 25, 24)}
REPEAT = 5
KEYS = {"gns": ("particles", "latent", "message_passing", "edges", "s_per_step",
                "graph_s_per_step", "threads")}


def lattice(dims, seed: int = 0) -> np.ndarray:
    g = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    return (g + 0.5) * SPACING_M + rng.normal(0, 0.02 * SPACING_M, g.shape)


def stats() -> dict:
    return {"vel_mean": [0.0] * 3, "vel_std": [6e-4] * 3, "acc_mean": [0.0] * 3,
            "acc_std": [3e-5] * 3, "friction_mean_deg": 32.0, "friction_std_deg": 5.0,
            "connectivity_radius_m": RADIUS_M, "frame_interval_s": 0.005,
            "bounds_m": [[0.0, 1.0]] * 3, "particle_spacing_m": SPACING_M, "input_velocities": 5}


def step_times(model: GNS, x: np.ndarray) -> tuple[int, float, float]:
    n = len(x)
    rng = np.random.default_rng(1)
    hist = x[:, None, :] + np.cumsum(rng.normal(0, 1e-4, (n, 6, 3)), axis=1)
    window = torch.tensor(hist, dtype=torch.float32)
    fr = torch.full((n,), 30.0)
    bounds = torch.tensor([[0.0, 1.0]] * 3)
    totals, graphs, edges = [], [], 0
    with torch.no_grad():
        for k in range(REPEAT + 1):
            t0 = time.perf_counter()
            s, r = radius_graph(window[:, -1].numpy(), RADIUS_M)
            t1 = time.perf_counter()
            nxt = model.next_positions(window, fr, bounds, torch.from_numpy(s),
                                       torch.from_numpy(r))
            window = torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)
            t2 = time.perf_counter()
            edges = len(s)
            if k:  # the first step compiles the graph kernels and warms the allocator
                totals.append(t2 - t0)
                graphs.append(t1 - t0)
    return edges, statistics.median(totals), statistics.median(graphs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, nargs="*", default=list(LATTICES))
    ap.add_argument("--latent", type=int, nargs="*", default=[128])
    ap.add_argument("--message-passing", type=int, nargs="*", default=[10])
    ap.add_argument("--no-tune", action="store_true", help="leave glibc malloc as it is")
    args = ap.parse_args()
    if not args.no_tune:
        tune_allocator()
    torch.manual_seed(0)
    for n in args.particles:
        x = lattice(LATTICES.get(n) or (round(n ** (1 / 3)),) * 3)
        for latent in args.latent:
            for m in args.message_passing:
                model = GNS(ModelConfig(latent=latent, message_passing=m), stats()).eval()
                edges, total, graph = step_times(model, x)
                print(json.dumps({"bench": "gns", "particles": len(x), "latent": latent,
                                  "message_passing": m, "edges": edges,
                                  "s_per_step": round(total, 4),
                                  "graph_s_per_step": round(graph, 4),
                                  "threads": torch.get_num_threads()}), flush=True)


if __name__ == "__main__":
    main()

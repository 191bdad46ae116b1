"""Pushforward training windows (Brandstetter, Worrall & Welling 2022, "Message passing
neural PDE solvers"): the model first rolls a window a few frames forward without
gradients, and the loss then asks for the true next velocity from the model's own inputs.
It learns to cancel the velocity drift its rollouts make (input noise only imitates that
drift), which decides where a deposit stops.
"""

from __future__ import annotations

import numpy as np
import torch

from gns.graph import radius_graph


def unroll(model, inputs: np.ndarray, friction_deg: float, bounds_m: np.ndarray,
           steps: int, device: str = "cpu") -> np.ndarray:
    """The last C+1 frames [n, C+1, 3] (m, float64) after `steps` frames predicted from
    `inputs` [n, C+1, 3] (m), each clamped to the domain as a rollout clamps it."""
    window = torch.as_tensor(inputs, dtype=torch.float32, device=device)
    n = window.shape[0]
    fr = torch.full((n,), float(friction_deg), device=device)
    bounds = torch.as_tensor(np.asarray(bounds_m), dtype=torch.float32, device=device)
    with torch.no_grad():
        for _ in range(steps):
            s, r = radius_graph(window[:, -1].cpu().numpy(), model.radius)
            nxt = model.next_positions(window, fr, bounds, torch.as_tensor(s, device=device),
                                       torch.as_tensor(r, device=device))
            nxt = torch.minimum(torch.maximum(nxt, bounds[:, 0]), bounds[:, 1])
            window = torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)
    out = window.cpu().numpy().astype(np.float64)
    if not np.isfinite(out).all():
        raise FloatingPointError(f"pushforward: non-finite positions after {steps} frames")
    return out


def draw_steps(rng: np.random.Generator, max_steps: int, prob: float) -> int:
    """Frames to unroll for one window: 0 (a plain window) or, with probability prob, 1 to
    max_steps uniformly."""
    if max_steps <= 0 or rng.random() >= prob:
        return 0
    return int(rng.integers(1, max_steps + 1))

"""Pushforward training windows (Brandstetter, Worrall & Welling 2022, "Message passing
neural PDE solvers"): the model first rolls a window a few frames forward without
gradients, and the loss then asks for the true next velocity from the model's own inputs.
It learns to cancel the velocity drift its rollouts make (input noise only imitates that
drift), which decides where a deposit stops.
"""

from __future__ import annotations

import numpy as np

from minority.gns.rollout import rollout


def unroll(model, inputs: np.ndarray, friction_deg: float, bounds_m: np.ndarray,
           steps: int, device: str = "cpu") -> np.ndarray:
    """The last C+1 frames [n, C+1, 3] (m, float64) after `steps` frames of gns.rollout from
    `inputs` [n, C+1, 3] (m): the same steps, domain clamping and divergence errors
    (RolloutError) as a validation rollout."""
    frames, _ = rollout(model, np.transpose(inputs, (1, 0, 2)), friction_deg, bounds_m, steps,
                        device=device)
    return np.transpose(frames[-inputs.shape[1]:], (1, 0, 2)).astype(np.float64)


def draw_steps(rng: np.random.Generator, max_steps: int, prob: float) -> int:
    """Frames to unroll for one window: 0 (a plain window) or, with probability prob, 1 to
    max_steps uniformly."""
    if max_steps <= 0 or rng.random() >= prob:
        return 0
    return int(rng.integers(1, max_steps + 1))

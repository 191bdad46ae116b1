"""An ensemble oracle: K rollouts of one scene, and the uncertainty the spec states from them.

One checkpoint ships, so the members are not several models: member 0 is the nominal
rollout (the prediction a single-rollout oracle uses) and members 1..K-1 start from
perturbed starts (`perturbed_starts`): "jitter" moves every particle of the C+1 history
frames by one random offset (std `jitter` particle spacings per axis, the same in every
history frame, so the history's velocities are kept); "friction" offsets the friction angle
(the model's material input) evenly within [-friction_deg, +friction_deg]; "both" alternates
the two. Measured on the 5 held-out scenes of the shipped checkpoint's test split
(`python -m bench.oracle_calibration`, docs/oracle.md, "Uncertainty"): jittered starts
barely spread the deposit (0 of 15 deposit measures inside the members' range), friction
offsets of +-2 deg spread it as much as the model errs (with intervals widened by their own
range on each side, 20 of 20 event times and 13 of 15 deposit measures inside); both
together (9 members) covered no more at widen 1 for twice the rollouts. So the defaults:
"friction", 5 members, widen 1 (gns.oracle.OracleOptions.interval_widen).

From the members (`gns.oracle.Oracle(..., members=...)` does the planning):
- `event_intervals`: per event, [min, max] of the members' times, widened on each side by
  `widen` times that range plus `pad_s`, within [0, the rollout's duration];
- `deposit_spread`: per member, the deposit's front (runout), height and largest
  displacement (gns.metrics.deposit, m) and their band, widened the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from minority.gns.metrics import deposit

PERTURBATIONS = ("jitter", "friction", "both")


@dataclass(frozen=True)
class EnsembleOptions:
    members: int = 5  # K, the nominal member included
    perturb: str = "friction"  # one of PERTURBATIONS (the calibrated choice: docstring)
    jitter: float = 0.1  # std of each particle's start offset per axis, particle spacings
    friction_deg: float = 2.0  # members' friction offsets span [-this, +this], deg
    seed: int = 0  # the jitter's random generator

    def __post_init__(self) -> None:
        if self.members < 1:
            raise ValueError(f"an ensemble needs at least 1 member, got {self.members}")
        if self.perturb not in PERTURBATIONS:
            raise ValueError(f"perturbation {self.perturb!r}: expected one of "
                             f"{', '.join(PERTURBATIONS)}")
        if not (self.jitter >= 0 and self.friction_deg >= 0):
            raise ValueError(f"jitter ({self.jitter}) and friction spread "
                             f"({self.friction_deg} deg) must be >= 0")


@dataclass(frozen=True)
class Member:
    history: np.ndarray  # [C+1, n, 3] m, the first frames the rollout starts from
    friction_deg: float
    label: dict  # what was perturbed: {"jitter_m": .., "friction_offset_deg": ..}


def friction_offsets(k: int, spread_deg: float) -> list[float]:
    """Offsets (deg) of k perturbed members: alternating in sign, growing in steps of
    spread / ceil(k / 2) up to the spread (k = 4: -s/2, +s/2, -s, +s; k = 3: -s/2, +s/2, -s),
    so that a smaller ensemble has the nearer ones and no member repeats the nominal."""
    half = max(1, -(-k // 2))
    return [(-1.0 if j % 2 else 1.0) * spread_deg * ((j + 1) // 2) / half
            for j in range(1, k + 1)]


def perturbed_starts(history: np.ndarray, friction_deg: float, spacing_m: float,
                     options: EnsembleOptions) -> list[Member]:
    """The ensemble's starts: member 0 the nominal (history [C+1, n, 3] m, friction_deg
    unchanged), then options.members - 1 perturbed ones: all jittered, all with friction
    offsets, or ("both") alternately one and the other, jittered first, so that "both" with
    2k + 1 members is "jitter" and "friction" with k + 1 each, together."""
    o = options
    rng = np.random.default_rng(o.seed)
    history = np.asarray(history, dtype=np.float64)
    k = o.members - 1
    kinds = {"jitter": ["jitter"] * k, "friction": ["friction"] * k,
             "both": ["jitter" if i % 2 == 0 else "friction" for i in range(k)]}[o.perturb]
    offsets = iter(friction_offsets(kinds.count("friction"), o.friction_deg))
    out = [Member(history, float(friction_deg), {"jitter_m": 0.0, "friction_offset_deg": 0.0})]
    for kind in kinds:
        if kind == "jitter":
            jitter_m = o.jitter * spacing_m  # the same offset in every history frame
            h = history + rng.normal(0.0, jitter_m, size=history.shape[1:])[None]
            out.append(Member(h, float(friction_deg),
                              {"jitter_m": jitter_m, "friction_offset_deg": 0.0}))
        else:
            df = next(offsets)
            out.append(Member(history, float(friction_deg) + df,
                              {"jitter_m": 0.0, "friction_offset_deg": df}))
    return out


def roll_members(model, starts: Sequence[Member], bounds_m: np.ndarray, frames: int, *,
                 device: str = "cpu", log=None, required: int = 1
                 ) -> tuple[list[np.ndarray], list[dict]]:
    """Roll each start out for `frames` frames (gns.rollout.rollout, one after another: the
    cost grows with the edges, so one batched graph would not be cheaper on a CPU). Returns
    the members' trajectories [C+1+frames, n, 3] (m, float32) and their labels, each with
    wall_s; a member that diverges is left out with a line on `log`, except the first
    `required` (the nominal): their RolloutError propagates."""
    import time

    from minority.gns.rollout import RolloutError, rollout

    trajectories, labels = [], []
    for i, m in enumerate(starts):
        t0 = time.perf_counter()
        try:
            pos, _ = rollout(model, m.history, m.friction_deg, bounds_m, frames, device=device)
        except RolloutError as exc:
            if i < required:
                raise
            if log is not None:
                print(f"ensemble: member {i} ({m.label}) left out: {exc}", file=log)
            continue
        trajectories.append(pos)
        labels.append({**m.label, "member": i, "wall_s": time.perf_counter() - t0})
        if log is not None:
            print(f"ensemble: member {i + 1}/{len(starts)} {m.label} in "
                  f"{labels[-1]['wall_s']:.1f} s", file=log, flush=True)
    return trajectories, labels


def band(values: Sequence[float], widen: float, pad: float = 0.0,
         lo: float = -np.inf, hi: float = np.inf) -> tuple[float, float]:
    """[min, max] of values widened on each side by widen * (max - min) + pad, clipped to
    [lo, hi]."""
    a, b = float(np.min(values)), float(np.max(values))
    w = widen * (b - a) + pad
    return max(a - w, lo), min(b + w, hi)


def event_intervals(member_times: Sequence[dict[str, float]], widen: float, pad_s: float,
                    duration_s: float) -> dict[str, tuple[float, float]]:
    """Per event name, the interval (s) the members' times span (member_times: one
    {name: time_s} per member), widened by `band`, within [0, duration_s]."""
    names = member_times[0].keys()
    return {n: band([t[n] for t in member_times], widen, pad_s, 0.0, duration_s)
            for n in names}


def deposit_spread(members: Sequence[np.ndarray], widen: float) -> dict:
    """The final deposit of each member [frames, n, 3] (m) and its band (`band`, no pad):
    {runout_m, height_m, displacement_max_m: {low, high, members}} (protocol.spec's
    DepositSpread as JSON)."""
    deposits = [deposit(m) for m in members]
    out = {}
    for key, attr in (("runout_m", "runout_m"), ("height_m", "height_m"),
                      ("displacement_max_m", "displacement_max_m")):
        values = [float(getattr(d, attr)) for d in deposits]
        low, high = band(values, widen)
        out[key] = {"low": low, "high": high, "members": values}
    return out

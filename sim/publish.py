"""The simulation's side of minority.insitu: the fields `minority sim` builds from its
ParticleState when `InSitu.due` says a step needs them (sim.ranks calls `connect`, `due`,
`publish`, `close`). The publishing itself (spec, cadences, culling, Stats, sender thread,
drop counts) is minority.insitu's.
"""

from __future__ import annotations

import functools

import numpy as np

from minority.insitu.payload import Particles
from minority.protocol.fields import FIELDS, FieldInfo
from minority.sim.state import ParticleState

# what the simulation can send: every field of the protocol's table (units, shapes)
SIM_FIELDS: dict[str, FieldInfo] = dict(FIELDS)


def sim_fields(ps: ParticleState, names, lazy: bool = False) -> dict:
    """The fields of `names` the particles give, float64, not copied where they are stored:
    velocity [n, 3] m/s (ps.v; also for velocity_magnitude), displacement [n, 3] m (x - x0;
    also for displacement_magnitude), pressure [n] Pa (-tr(tau) / 3). Others are skipped
    (`id` comes from the ids; unknown names are the publisher's to report). lazy: the
    computed ones (displacement, pressure) as functions of the current arrays, for a lent
    step (InSitu.publish(copy=False)) whose sender computes them."""
    out: dict = {}
    for name in names:
        base = name.removesuffix("_magnitude")
        if base == "velocity":
            out["velocity"] = ps.v
        elif base == "displacement" and "displacement" not in out:
            out["displacement"] = functools.partial(np.subtract, ps.x, ps.x0)
        elif name == "pressure":
            out["pressure"] = functools.partial(_pressure, ps.tau)
    if not lazy:
        out = {k: v() if callable(v) else v for k, v in out.items()}
    return out


def _pressure(tau: np.ndarray) -> np.ndarray:
    """[n] Pa from the Cauchy stress tau [n, 3, 3] Pa."""
    return -(tau[:, 0, 0] + tau[:, 1, 1] + tau[:, 2, 2]) / 3.0


def sim_particles(ps: ParticleState, names=SIM_FIELDS) -> Particles:
    """The particles as insitu's publisher takes them, with the fields of `names`."""
    return Particles(ps.x, ps.pid, sim_fields(ps, names))

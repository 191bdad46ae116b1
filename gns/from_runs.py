"""The GNS dataset from any simulator's runs: HDF5 files in the layout of
minority.protocol.trajectory (read_trajectory: positions, frame interval and bounds required;
particle type, material and spacing optional), packed by gns.dataset.pack.

What the model takes from a run: the positions of the particles it moves (kinematic ones,
GNS type 3, are left out: the domain's faces are its walls), one friction angle (the
`material` dataset, the same for every particle, or `friction_deg` for runs without one),
the domain bounds, and the particle spacing (the file's, else estimated from frame 0).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from minority.gns.dataset import SPLITS, DatasetError, Packed, pack
from minority.protocol.trajectory import (
    PARTICLE_TYPE_KINEMATIC,
    RunTrajectory,
    read_trajectory,
)

RADIUS_PER_SPACING = 0.029 / 0.016  # the shipped model's connectivity radius / spacing
SPACING_RTOL = 0.05  # runs of one dataset may differ this much in particle spacing
SPACING_SAMPLE = 512  # particles whose nearest-neighbour distance estimates the spacing


def estimate_spacing(x: np.ndarray, seed: int = 0) -> float:
    """The median nearest-neighbour distance (m) of up to SPACING_SAMPLE particles drawn from
    x [n, 3] (m): the seeding spacing of a lattice, about the grain diameter of a packing."""
    x = np.asarray(x, np.float64)
    if len(x) < 2:
        raise DatasetError("one particle has no spacing: add attr particle_spacing_m (m)")
    pick = np.random.default_rng(seed).permutation(len(x))[:SPACING_SAMPLE]
    nearest = np.empty(len(pick))
    for k in range(0, len(pick), 16):  # [16, n] distances at a time
        rows = pick[k:k + 16]
        d = ((x[rows, None, :] - x[None, :, :]) ** 2).sum(-1)
        d[np.arange(len(rows)), rows] = np.inf
        nearest[k:k + 16] = np.sqrt(d.min(axis=1))
    spacing = float(np.median(nearest))
    if not spacing > 0:
        raise DatasetError("particles coincide at frame 0: add attr particle_spacing_m (m)")
    return spacing


def collect(sources: Iterable[str | Path], valid: int = 1, test: int = 0) -> list[tuple[str, Path]]:
    """[(split, file)] from sources, each a .h5 file or a folder of them. A folder with
    train/, valid/ or test/ subfolders gives its files those splits; the other files, sorted
    by name, are train but for the last `test` (test) and the `valid` before them (valid)."""
    split_of, loose = [], []
    for src in map(Path, sources):
        if src.is_file():
            loose.append(src)
        elif src.is_dir():
            subs = [s for s in SPLITS if (src / s).is_dir()]
            for s in subs:
                split_of += [(s, p) for p in sorted((src / s).glob("*.h5"))]
            if not subs:
                loose += sorted(src.glob("*.h5"))
        else:
            raise DatasetError(f"{src}: no such file or directory")
    loose = sorted(set(loose), key=lambda p: (p.name, str(p)))
    if valid < 0 or test < 0:
        raise DatasetError(f"valid {valid} and test {test} must be >= 0")
    if loose and len(loose) <= valid + test:
        raise DatasetError(f"{len(loose)} runs cannot give {valid} valid and {test} test runs "
                           "and still train on one: lower valid / test")
    cut = len(loose) - valid - test
    split_of += [("train" if i < cut else "valid" if i < cut + valid else "test", p)
                 for i, p in enumerate(loose)]
    if not split_of:
        raise DatasetError(f"no .h5 runs in {', '.join(map(str, sources))}")
    return split_of


def friction_of(run: RunTrajectory, path: Path, keep: np.ndarray,
                friction_deg: float | None) -> float:
    """The run's one friction angle (deg): its material, the same on every particle kept, or
    friction_deg when it has none."""
    if run.material is None:
        if friction_deg is None:
            raise DatasetError(f"{path}: no material dataset (friction angle per particle, "
                               "deg): add it, or give the runs' friction angle (--friction-deg)")
        return float(friction_deg)
    phi = run.material[keep]
    if np.ptp(phi) > 1e-6 * max(1.0, float(np.abs(phi).max())):
        raise DatasetError(f"{path}: material varies within the run ({phi.min():g} to "
                           f"{phi.max():g} deg); the model takes one friction angle per run")
    return float(phi[0])


def to_packed(run: RunTrajectory, path: Path, split: str, friction_deg: float | None = None,
              spacing_m: float | None = None) -> Packed:
    """A checked run as the dataset stores it: kinematic particles left out, one particle
    type kept (the model has no type feature), one friction angle; spacing_m (m): the run's
    spacing when it is known already (else its attr, else estimated)."""
    keep = run.particle_type != PARTICLE_TYPE_KINEMATIC
    types = np.unique(run.particle_type[keep]).tolist()
    if not types:
        raise DatasetError(f"{path}: every particle is kinematic (type "
                           f"{PARTICLE_TYPE_KINEMATIC}); there is nothing for the model to move")
    if len(types) > 1:
        raise DatasetError(f"{path}: particle types {types}; the model moves one material "
                           f"(kinematic type {PARTICLE_TYPE_KINEMATIC} aside)")
    pos = run.positions[:, keep] if not keep.all() else run.positions
    phi = friction_of(run, path, keep, friction_deg)
    spacing = run.particle_spacing_m or spacing_m or estimate_spacing(pos[0])
    return Packed(run.name, split, pos, phi, run.bounds_m, run.frame_interval_s, spacing,
                  particle_type=run.particle_type[keep],
                  scene={"source": str(path), "kinematic_left_out": int((~keep).sum()),
                         "particle_spacing_m": spacing,
                         "spacing_estimated": run.particle_spacing_m is None})


def build_from_runs(sources: Iterable[str | Path], out_dir: str | Path, *, stride: int = 1,
                    valid: int = 1, test: int = 0, connectivity_radius_m: float | None = None,
                    friction_deg: float | None = None, log=None) -> dict:
    """Pack the runs of `sources` (collect) into a dataset at out_dir, every stride-th frame;
    connectivity radius RADIUS_PER_SPACING x the particle spacing unless given (m). Returns
    the metadata. Raises DatasetError, TrajectoryError (both ValueError)."""
    log = sys.stderr if log is None else log
    runs = collect(sources, valid, test)
    if stride < 1:
        raise DatasetError(f"stride {stride} must be >= 1")
    if connectivity_radius_m is not None and not connectivity_radius_m > 0:
        raise DatasetError(f"connectivity radius {connectivity_radius_m} m must be > 0")
    spacings = {}
    if connectivity_radius_m is None:  # a first pass: the spacing decides the radius
        spacings = {p: _spacing(p) for _, p in runs}
        connectivity_radius_m = round(RADIUS_PER_SPACING * float(np.median(list(spacings.values()))), 9)
    items = (to_packed(read_trajectory(p, stride), p, s, friction_deg, spacings.get(p))
             for s, p in runs)
    return pack(items, out_dir, connectivity_radius_m=connectivity_radius_m,
                spacing_rtol=SPACING_RTOL, log=log,
                meta={"config": "", "sources": [str(p) for _, p in runs]})


def _spacing(path: Path) -> float:
    """A run's particle spacing (m): its attr, else estimated from its first frame."""
    run = read_trajectory(path, stride=10**9)  # frame 0 only
    if run.particle_spacing_m:
        return run.particle_spacing_m
    keep = run.particle_type != PARTICLE_TYPE_KINEMATIC
    return estimate_spacing(run.positions[0, keep])


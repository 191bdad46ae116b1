"""GNS dataset: MPM trajectories packed per split, with the metadata the model is built from.

Layout of a dataset directory:

    metadata.json   dim, bounds, connectivity radius, frame interval, normalization
                    statistics, the scenes of every split, units
    train.h5        one group per scene: positions [frames, n, 3] float32 (m),
    valid.h5        attrs friction_angle_deg, bounds_m [3, 2] (m), and the scene's geometry
    test.h5

Model units: positions in m, velocity = displacement per frame (m/frame), acceleration =
change of that per frame (m/frame^2); frame = `frame_interval_s`.
"""

from __future__ import annotations

import itertools
import json
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from minority.gns.metrics import deposit
from minority.protocol.trajectory import read_sim

FORMAT = "minority-gns-dataset/1"
SPLITS = ("train", "valid", "test")
INPUT_VELOCITIES = 5  # C: velocities of the last C frames are node features
STD_FLOOR = 1e-12  # m/frame (or m/frame^2): a component that never varies still normalizes


class DatasetError(ValueError):
    """A dataset or trajectory that cannot be read or does not match the metadata."""


@dataclass
class Trajectory:
    name: str
    positions: np.ndarray  # [frames, n, 3] float32, m
    friction_angle_deg: float
    bounds_m: np.ndarray  # [3, 2] lo, hi per axis, m


COARSE_GRAIN_METHODS = ("mean", "sample")


def coarse_grain(positions: np.ndarray, spacing_m: float, factor: int, method: str = "mean",
                 seed: int = 0) -> np.ndarray:
    """[frames, m, 3]: one particle per group of particles that start in one cube of edge
    factor * spacing_m (a cube of the lattice anchored at the origin), from positions
    [frames, n, 3] (m) of particles seeded at spacing_m; frame 0 is the seeding. Method
    "mean": the group's mean position. Method "sample": one member drawn per group (seeded),
    shifted by its offset from the group's mean at frame 0, so it starts where the mean does
    but moves as a material point of the run; unlike the mean, it keeps the spread within
    groups, so high quantiles of the sample (a deposit's front) estimate the run's. A body
    whose extent is a whole number of cubes gives factor^3 particles per group, and frame 0
    lies on the lattice (i + 1/2) * factor * spacing_m: the particles a run at that spacing
    seeds. Groups are ordered by their cube (x, then y, then z)."""
    if method not in COARSE_GRAIN_METHODS:
        raise DatasetError(f"coarse-grain method {method!r}, expected one of "
                           f"{', '.join(COARSE_GRAIN_METHODS)}")
    if factor == 1:
        return positions
    cube = np.floor(positions[0].astype(np.float64) / (factor * spacing_m) + 1e-6).astype(np.int64)
    keys, group = np.unique(cube, axis=0, return_inverse=True)
    group = group.reshape(-1)
    counts = np.bincount(group, minlength=len(keys))
    means = np.empty((positions.shape[0] if method == "mean" else 1, len(keys), 3))
    for a in range(3):
        for k in range(means.shape[0]):
            means[k, :, a] = np.bincount(group, positions[k, :, a], minlength=len(keys)) / counts
    if method == "mean":
        return means
    order = np.argsort(group, kind="stable")  # members of group g: order[start[g]:][:counts[g]]
    start = np.concatenate(([0], np.cumsum(counts)[:-1]))
    pick = order[start + np.random.default_rng(seed).integers(0, counts)]
    offset = positions[0, pick].astype(np.float64) - means[0]  # [m, 3]
    return positions[:, pick].astype(np.float64) - offset


def read_sim_trajectory(path: Path, stride: int, factor: int = 1,
                        method: str = "mean") -> tuple[np.ndarray, dict]:
    """Positions every stride-th frame [frames, n, 3], coarse-grained by `factor` with
    `method` (coarse_grain), and the run's attributes (protocol.trajectory.read_sim;
    particle_spacing_m: after coarse-graining; mpm_deposit: gns.metrics.deposit of the run
    itself, before coarse-graining)."""
    try:
        pos, attrs = read_sim(path, stride)
    except (OSError, KeyError) as exc:
        raise DatasetError(f"{path}: cannot read the MPM run ({exc})") from None
    if not np.isfinite(pos).all():
        raise DatasetError(f"{path}: non-finite positions")
    spacing = float(attrs["particle_spacing_m"])
    attrs["mpm_particle_spacing_m"] = spacing
    attrs["particle_spacing_m"] = spacing * factor
    attrs["mpm_deposit"] = deposit(pos).as_dict()
    return coarse_grain(pos, spacing, factor, method).astype(np.float32), attrs


def _stats(trajs: list[np.ndarray]) -> dict:
    vel_sum = np.zeros(3)
    vel_sq = np.zeros(3)
    acc_sum = np.zeros(3)
    acc_sq = np.zeros(3)
    nv = na = 0
    for pos in trajs:
        p = pos.astype(np.float64)
        v = np.diff(p, axis=0)
        a = np.diff(v, axis=0)
        vel_sum += v.sum(axis=(0, 1))
        vel_sq += (v * v).sum(axis=(0, 1))
        acc_sum += a.sum(axis=(0, 1))
        acc_sq += (a * a).sum(axis=(0, 1))
        nv += v.shape[0] * v.shape[1]
        na += a.shape[0] * a.shape[1]
    vm, am = vel_sum / nv, acc_sum / na

    def std(sq, n, mean):  # the variance clipped at 0 (cancellation), the std kept above 0
        return np.maximum(np.sqrt(np.maximum(sq / n - mean * mean, 0.0)), STD_FLOOR).tolist()

    return {"vel_mean": vm.tolist(), "vel_std": std(vel_sq, nv, vm),
            "acc_mean": am.tolist(), "acc_std": std(acc_sq, na, am)}


@dataclass
class Packed:
    """One trajectory as the dataset stores it."""

    name: str
    split: str  # one of SPLITS
    positions: np.ndarray  # [frames, n, 3] float32, m
    friction_angle_deg: float
    bounds_m: np.ndarray  # [3, 2] lo, hi per axis, m
    frame_interval_s: float  # s
    particle_spacing_m: float  # m
    particle_type: np.ndarray | None = None  # [n] int; None: all PARTICLE_TYPE_SAND
    attrs: dict = field(default_factory=dict)  # more group attrs (floats)
    scene: dict = field(default_factory=dict)  # more fields of the metadata's scene entry


def pack(items: Iterable[Packed], out_dir: str | Path, *, connectivity_radius_m: float,
         spacing_rtol: float = 0.0, meta: dict | None = None, log=None) -> dict:
    """Write trajectories, one at a time, into out_dir (train.h5, valid.h5, test.h5,
    metadata.json) and return the metadata: its statistics from the train split, `meta`'s
    keys added. One dataset has one frame interval; particle spacings may differ by
    spacing_rtol (relative; the metadata records their median)."""
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    items = iter(items)
    first = next(items, None)  # a first run that cannot be read leaves nothing behind
    if first is None:
        raise DatasetError("no trajectories to pack")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {s: h5py.File(out / f"{s}.h5", "w") for s in SPLITS}
    scenes, train_pos, frame_dt, spacing, phis = [], [], set(), [], []
    bounds_hi = np.zeros(3)
    try:
        for it in itertools.chain([first], items):
            pos = it.positions
            if it.split not in SPLITS:
                raise DatasetError(f"{it.name}: split {it.split!r}, expected one of {SPLITS}")
            if it.name in files[it.split]:
                raise DatasetError(f"two {it.split} trajectories named {it.name!r}")
            if pos.shape[0] < 2:
                raise DatasetError(f"{it.name}: {pos.shape[0]} frame(s); a trajectory needs 2")
            if pos.shape[0] < INPUT_VELOCITIES + 2:
                print(f"dataset: note: {it.name} has {pos.shape[0]} frames, fewer than a "
                      f"training window's {INPUT_VELOCITIES + 2}: it gives no training sample",
                      file=log)
            frame_dt.add(round(float(it.frame_interval_s), 12))
            spacing.append(float(it.particle_spacing_m))
            g = files[it.split].create_group(it.name)
            g.create_dataset("positions", data=pos, chunks=(1, *pos.shape[1:]))
            if it.particle_type is not None:
                g.create_dataset("particle_type", data=np.asarray(it.particle_type, np.int32))
            g.attrs["friction_angle_deg"] = float(it.friction_angle_deg)
            g.attrs["bounds_m"] = np.asarray(it.bounds_m, np.float64)
            for key, value in it.attrs.items():
                g.attrs[key] = value
            bounds_hi = np.maximum(bounds_hi, np.asarray(it.bounds_m)[:, 1])
            if it.split == "train":
                train_pos.append(pos)
                phis.append(float(it.friction_angle_deg))
            scenes.append({"name": it.name, "split": it.split, "particles": pos.shape[1],
                           "frames": pos.shape[0],
                           "friction_angle_deg": float(it.friction_angle_deg), **it.scene})
            print(f"dataset: {it.split}/{it.name} {pos.shape[0]} frames x {pos.shape[1]} "
                  "particles", file=log, flush=True)
    finally:
        for f in files.values():
            f.close()
    lo, hi = (min(spacing), max(spacing)) if spacing else (0.0, 0.0)
    if len(frame_dt) > 1 or hi - lo > spacing_rtol * lo + 1e-9 * hi:
        raise DatasetError(f"runs differ in frame interval {sorted(frame_dt)} s or particle "
                           f"spacing {sorted(set(spacing))} m; one dataset needs one of each")
    if not train_pos:
        raise DatasetError("no train scenes")
    meta = {
        "format": FORMAT, "dim": 3, "input_velocities": INPUT_VELOCITIES,
        "bounds_m": [[0.0, float(h)] for h in bounds_hi],
        "connectivity_radius_m": connectivity_radius_m,
        "particle_spacing_m": float(np.median(spacing)), "frame_interval_s": frame_dt.pop(),
        "coarse_grain": 1, "coarse_grain_method": "mean",
        **_stats(train_pos),
        # one friction angle in every train scene: the feature is 0, its scale 1 (not 0/0)
        "friction_mean_deg": float(np.mean(phis)), "friction_std_deg": float(np.std(phis)) or 1.0,
        "scenes": scenes, "config": "",
        "units": {"positions": "m", "velocity": "m/frame", "acceleration": "m/frame^2",
                  "frame_interval_s": "s", "friction": "deg"},
        **(meta or {}),
    }
    (out / "metadata.json").write_text(json.dumps(meta, indent=1))
    return meta


def build(runs: list[tuple[object, Path]], out_dir: str | Path, *, stride: int,
          connectivity_radius_m: float, config_path: str = "", coarse_grain: int = 1,
          coarse_grain_method: str = "mean", log=None) -> dict:
    """Pack finished sweep runs [(ScenePlan, HDF5 path)] into out_dir, coarse-grained by
    `coarse_grain` (1: as run) with `coarse_grain_method`; return the metadata."""

    def items():
        for plan, path in runs:
            pos, attrs = read_sim_trajectory(path, stride, coarse_grain, coarse_grain_method)
            geometry = {k: float(getattr(plan, k))
                        for k in ("length_m", "width_m", "height_m", "aspect_ratio")}
            yield Packed(plan.name, plan.split, pos, attrs["friction_angle_deg"],
                         np.asarray(attrs["bounds_m"], np.float64),
                         float(attrs["output_interval_s"]) * stride,
                         round(float(attrs["particle_spacing_m"]), 9), attrs=geometry,
                         scene={"aspect_ratio": round(plan.aspect_ratio, 4),
                                "length_m": plan.length_m, "width_m": plan.width_m,
                                "height_m": plan.height_m, "source": str(path),
                                # the MPM run's own deposit, at its resolution (the model's
                                # data are coarse-grained from it when coarse_grain > 1)
                                "mpm_deposit": attrs["mpm_deposit"]})

    return pack(items(), out_dir, connectivity_radius_m=connectivity_radius_m, log=log,
                meta={"coarse_grain": coarse_grain, "coarse_grain_method": coarse_grain_method,
                      "config": str(config_path)})


def load_metadata(path: str | Path) -> dict:
    path = Path(path)
    try:
        meta = json.loads((path / "metadata.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read metadata.json ({exc})") from None
    if meta.get("format") != FORMAT:
        raise DatasetError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
    return meta


def load_split(path: str | Path, split: str) -> list[Trajectory]:
    """Every trajectory of a split, in memory."""
    trajs = []
    with h5py.File(Path(path) / f"{split}.h5", "r") as f:
        for name in sorted(f):
            g = f[name]
            trajs.append(Trajectory(name, g["positions"][...],
                                    float(g.attrs["friction_angle_deg"]),
                                    np.asarray(g.attrs["bounds_m"], np.float64)))
    return trajs

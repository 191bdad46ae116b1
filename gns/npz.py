"""The npz layout of geoelements/gns (Kumar & Vantassel's GNS), read and written, so data and
models move between that project and this one.

Their dataset directory:

    train.npz, valid.npz, test.npz   one entry per trajectory, each a 2- or 3-element object
                                     array (positions [T, n, dim] float, particle_type [n]
                                     int or one int, material_property optional: one value
                                     or [n]; their ColumnCollapseFrictional data hold
                                     tan(friction angle)); or one entry "gns_data" holding
                                     every trajectory
    metadata.json   bounds [dim, 2], sequence_length, default_connectivity_radius, dim, dt,
                    vel_mean / vel_std / acc_mean / acc_std ([dim]: per-frame position
                    differences, the units of ours), optional material_feature_len, nnode_in,
                    nedge_in; optionally all of it under "train" and "rollout"

How their code reads it (geoelements/gns, gns/train.py and gns/learned_simulator.py):

- rollout (train.py predict, read_metadata(path, "rollout")): `metadata["sequence_length"]`
  is read with [] (the key must be there); an int gives nsteps = sequence_length - 6 for
  every test trajectory and is compared with positions[6:], so it must be the frame count
  T; null takes each trajectory's own T.
- walls (train.py _get_simulator -> LearnedSimulator._encoder_preprocessor): one `bounds`
  per model; the node features are the distances to those six faces over the radius,
  clamped to [-1, 1]. A face more than one radius from the particles is not seen.

So a trajectory's walls are where gns sees them only in a dataset whose `bounds` are its
own: export writes one dataset per domain (DIR itself when every scene shares one, else
DIR/domain_00, DIR/domain_01, ... each a complete dataset of theirs), `sequence_length`
the frame count of its trajectories (null where they differ). Import reads either layout.

Their loader unpickles the object arrays; ours reads them with an unpickler that builds
numpy arrays and nothing else, so a file cannot run code here. Export writes what their
loader reads, plus a "minority" section in metadata.json (per-scene bounds and friction,
spacing) that import reads back. Import keeps the keys of their metadata.json that our
dataset does not derive (normalization statistics, boundary_augment, ...) and export
writes them back, so gns -> minority -> gns keeps every key of theirs.
"""

from __future__ import annotations

import json
import math
import pickle
import sys
import zipfile
from pathlib import Path

import numpy as np

from minority.gns.dataset import SPLITS, DatasetError, load_metadata, load_split, pack
from minority.gns.from_runs import to_packed
from minority.protocol.trajectory import PARTICLE_TYPE_SAND, RunTrajectory

MATERIAL_ENCODINGS = ("tan_phi", "deg", "none")  # the material_property of a trajectory
# node inputs of their 3D model without material: 5 velocities x 3, 6 wall distances, a
# 16-wide particle-type embedding; edges: the 3 components of the displacement and its norm
NNODE_IN_3D, NEDGE_IN_3D = 37, 4
_NUMPY_GLOBALS = {("multiarray", "_reconstruct"), ("multiarray", "scalar"),
                  ("numeric", "_frombuffer")}


class NpzError(DatasetError):
    """An npz dataset that cannot be read, or a dataset that cannot be written as one."""


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays, dtypes and scalars only: any other global is refused."""

    def find_class(self, module: str, name: str):
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module == "_codecs" and name == "encode":  # bytes as pickle protocol 2 writes them
            return super().find_class(module, name)
        head, _, tail = module.rpartition(".")
        if head in ("numpy.core", "numpy._core") and (tail, name) in _NUMPY_GLOBALS:
            return super().find_class(f"numpy._core.{tail}" if hasattr(np, "_core")
                                      else module, name)
        raise pickle.UnpicklingError(f"refused: the file pickles {module}.{name}, not an array")


def _read_member(zf: zipfile.ZipFile, member: str):
    with zf.open(member) as fp:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            _, _, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            _, _, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            dtype = None
        if dtype is not None and dtype.hasobject:
            return _ArrayUnpickler(fp).load()
    with zf.open(member) as fp:
        return np.lib.format.read_array(fp, allow_pickle=False)


def load_npz(path: str | Path) -> dict[str, tuple]:
    """{name: (positions, particle_type[, material_property])} of one npz file of theirs,
    in the file's order. Raises NpzError."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            raw = {m.removesuffix(".npy"): _read_member(zf, m) for m in zf.namelist()}
    except (OSError, zipfile.BadZipFile, ValueError, EOFError, pickle.UnpicklingError,
            AttributeError, TypeError) as exc:
        raise NpzError(f"{path}: cannot read the npz ({exc})") from None
    if "gns_data" in raw:
        raw = {f"{path.stem}_{i:03d}": t for i, t in enumerate(raw["gns_data"])}
    out = {}
    for name, item in raw.items():
        if len(item) not in (2, 3):
            raise NpzError(f"{path}: {name} holds {len(item)} items; expected (positions, "
                           "particle_type[, material_property])")
        out[name] = tuple(item)
    if not out:
        raise NpzError(f"{path}: no trajectories")
    return out


# keys of their metadata.json that our dataset derives from its trajectories; import keeps
# the others (normalization statistics, boundary_augment, ...) and export writes them back
DERIVED_KEYS = frozenset({"bounds", "sequence_length", "default_connectivity_radius", "dim",
                          "dt", "material_feature_len", "nnode_in", "nedge_in", "minority"})
STATS_KEYS = ("vel_mean", "vel_std", "acc_mean", "acc_std")


def _read_metadata(src: Path) -> dict:
    try:
        raw = json.loads((src / "metadata.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise NpzError(f"{src}: cannot read metadata.json ({exc})") from None
    if not isinstance(raw, dict):
        raise NpzError(f"{src}/metadata.json: expected a JSON object")
    return raw


def _section(raw: dict, purpose: str) -> dict:
    """What their read_metadata(path, purpose) returns (gns/reading_utils.py: raw[purpose]
    when the file is split by purpose, else all of it; the "train" section where only that
    one is there), with our section added."""
    sec = next((raw[p] for p in (purpose, "train") if isinstance(raw.get(p), dict)), raw)
    return {**sec, "minority": raw.get("minority")}


def _domains(src: Path) -> list[Path]:
    """The dataset directories of theirs at src: src itself, or each subdirectory that
    holds a metadata.json (export's one dataset per domain)."""
    if (src / "metadata.json").is_file():
        return [src]
    subs = sorted(d for d in src.iterdir() if (d / "metadata.json").is_file()) \
        if src.is_dir() else []
    if not subs:
        raise NpzError(f"{src}: no metadata.json, in it or in a subdirectory")
    return subs


def _run(name: str, split: str, item: tuple, meta: dict, where: str, *, material: str,
         frame_interval_s: float) -> RunTrajectory:
    pos = np.asarray(item[0])
    if pos.ndim != 3 or pos.dtype.kind not in "fiu":
        raise NpzError(f"{where}: {name} positions must be [T, n, dim] numbers, got "
                       f"{list(pos.shape)} {pos.dtype}")
    if pos.shape[2] != 3:
        raise NpzError(f"{where}: {name} is {pos.shape[2]}D; the minority GNS is 3D")
    n = pos.shape[1]
    ptype = np.broadcast_to(np.asarray(item[1]), (n,))
    if ptype.dtype.kind not in "iu":
        raise NpzError(f"{where}: {name} particle_type must be integers, got {ptype.dtype}")
    phi = None
    if len(item) == 3 and material != "none":
        prop = np.asarray(item[2], np.float64).reshape(-1)
        if prop.size not in (1, n):
            raise NpzError(f"{where}: {name} material_property has {prop.size} values for "
                           f"{n} particles; one friction value (per particle) expected")
        prop = np.broadcast_to(prop, (n,))
        phi = np.degrees(np.arctan(prop)) if material == "tan_phi" else prop
    ours = meta.get("minority") or {}
    scene = (ours.get("scenes") or {}).get(split, {}).get(name, {})  # what export wrote
    bounds = np.asarray(scene.get("bounds_m", meta.get("bounds")), np.float64)
    if bounds.shape != (3, 2):
        raise NpzError(f"{where}: metadata.json bounds must be [3, 2] lo, hi per axis, got "
                       f"{meta.get('bounds')!r}")
    spacing = ours.get("particle_spacing_m")
    return RunTrajectory(name, pos.astype(np.float32), frame_interval_s, bounds,
                         ptype.astype(np.int32), None if phi is None else phi.astype(np.float32),
                         None if spacing is None else float(spacing))


def import_npz(src: str | Path, out_dir: str | Path, *, material: str = "tan_phi",
               frame_interval_s: float | None = None, friction_deg: float | None = None,
               connectivity_radius_m: float | None = None, log=None) -> dict:
    """Their dataset directory src (train.npz, optional valid.npz / test.npz, metadata.json;
    or subdirectories that each are one, as export writes several domains) -> our dataset at
    out_dir; material: how their material_property encodes the friction angle
    (MATERIAL_ENCODINGS). Positions are taken as m, dt as the frame interval (s) unless
    frame_interval_s is given. A trajectory's walls are its metadata's bounds: "train" for
    the train and valid splits, "rollout" for test where the file is split by purpose (as
    their trainer and rollout read them). Returns our metadata."""
    src, log = Path(src), sys.stderr if log is None else log
    if material not in MATERIAL_ENCODINGS:
        raise NpzError(f"material {material!r}, expected one of {', '.join(MATERIAL_ENCODINGS)}")
    domains = []  # (where, metadata.json, frame interval s, {split: {name: item}})
    radii = set()
    for d in _domains(src):
        raw = _read_metadata(d)
        train_meta = _section(raw, "train")
        if int(train_meta.get("dim", 3)) != 3:
            raise NpzError(f"{d}: dim {train_meta.get('dim')}; the minority GNS is 3D")
        dt = frame_interval_s if frame_interval_s is not None else train_meta.get("dt")
        if dt is None or not math.isfinite(float(dt)) or float(dt) <= 0:
            raise NpzError(f"{d}: metadata.json dt {dt!r} is not a frame interval > 0 (s): "
                           "give one (--frame-interval)")
        radius = connectivity_radius_m or train_meta.get("default_connectivity_radius")
        if radius is None or not float(radius) > 0:
            raise NpzError(f"{d}: no default_connectivity_radius in metadata.json: give one "
                           "(--radius)")
        radii.add(float(radius))
        # all read and checked before anything is written
        splits = {s: load_npz(d / f"{s}.npz") for s in SPLITS if (d / f"{s}.npz").is_file()}
        domains.append((d, raw, float(dt), splits))
    if not any("train" in splits for *_, splits in domains):
        raise NpzError(f"{src}: no train.npz")
    if len(radii) > 1:
        raise NpzError(f"{src}: the domains' default_connectivity_radius differ "
                       f"{sorted(radii)}; give one (--radius)")
    first = domains[0][1]  # what export writes back: their keys that ours does not derive
    carried = {p: {k: v for k, v in _section(first, p).items() if k not in DERIVED_KEYS}
               for p in ("train", "rollout") if p == "train" or _by_purpose(first)}

    def items():
        for d, raw, dt, splits in domains:
            for split, trajs in splits.items():
                meta = _section(raw, "rollout" if split == "test" else "train")
                where = str(d / f"{split}.npz")
                for name, item in trajs.items():
                    run = _run(name, split, item, meta, where, material=material,
                               frame_interval_s=dt)
                    p = to_packed(run, Path(where), split, friction_deg)
                    p.scene["source"] = f"{where}:{name}"
                    yield p

    return pack(items(), out_dir, connectivity_radius_m=radii.pop(), log=log,
                spacing_rtol=0.05, meta={"config": "", "imported_from": str(src),
                                         "gns_metadata": carried})


def _by_purpose(raw: dict) -> bool:
    return isinstance(raw.get("train"), dict) and isinstance(raw.get("rollout"), dict)


def export_npz(dataset: str | Path, out_dir: str | Path, *, material: str = "tan_phi") -> dict:
    """Our dataset -> their layout, where gns sees each trajectory's own walls: one dataset
    of theirs at out_dir when all scenes share bounds, or when the train and valid scenes
    share one and the test scenes another (metadata.json split into "train" and "rollout",
    as their trainer and rollout read it); else one per domain (scenes with one set of
    bounds), out_dir/domain_00, domain_01, ... Each holds {split}.npz per split it has (one
    entry per scene, in the dataset's order: positions [T, n, 3] float32 m, particle_type [n]
    int64, and unless material is "none" the friction angle as tan(phi) or in degrees) and
    metadata.json (bounds the scenes', sequence_length their frame count or null where they
    differ). Returns {"datasets": {directory relative to out_dir: metadata.json written},
    "dt": s, "default_connectivity_radius": m, "minority": {"scenes": {split: {name: ...}}}}."""
    if material not in MATERIAL_ENCODINGS:
        raise NpzError(f"material {material!r}, expected one of {', '.join(MATERIAL_ENCODINGS)}")
    meta = load_metadata(dataset)
    members = []  # [(split, Trajectory)] in the dataset's order
    for split in SPLITS:
        try:
            trajs = {t.name: t for t in load_split(dataset, split)}
        except OSError as exc:
            raise NpzError(f"{dataset}: cannot read the {split} split ({exc})") from None
        listed = [sc["name"] for sc in meta.get("scenes", ()) if sc.get("split") == split]
        members += [(split, trajs[n]) for n in [n for n in listed if n in trajs]
                    + sorted(set(trajs) - set(listed))]
    if not members:
        raise NpzError(f"{dataset}: no trajectories")
    domains: dict[tuple, list] = {}  # bounds -> members
    for split, t in members:
        domains.setdefault(_bounds_key(t), []).append((split, t))
    gns = meta.get("gns_metadata") or {}  # their keys, where the dataset was theirs
    fit = [{_bounds_key(t) for s, t in members if (s == "test") == test} for test in (False, True)]
    by_purpose = len(fit[0]) == len(fit[1]) == 1 and (fit[0] != fit[1] or "rollout" in gns)
    features = 0 if material == "none" else 1
    base = {
        "default_connectivity_radius": meta["connectivity_radius_m"], "dim": 3,
        "dt": meta["frame_interval_s"], **{k: meta[k] for k in STATS_KEYS},
        "nnode_in": NNODE_IN_3D + features, "nedge_in": NEDGE_IN_3D,
        **({"material_feature_len": features} if features else {}),
    }
    carried = {p: {k: v for k, v in gns.get(p, gns.get("train", {})).items()
                   if k not in DERIVED_KEYS} for p in ("train", "rollout")}
    ours = {"format": meta["format"], "material": material,
            "particle_spacing_m": meta["particle_spacing_m"],
            "friction_mean_deg": meta["friction_mean_deg"],
            "friction_std_deg": meta["friction_std_deg"],
            "units": {"positions": "m", "dt": "s", "velocity": "m/frame",
                      "acceleration": "m/frame^2", "bounds": "m"}}
    out = Path(out_dir)
    groups = {".": members} if by_purpose or len(domains) == 1 else \
        {f"domain_{k:02d}": m for k, m in enumerate(domains.values())}
    if stale := _stale(out, groups):
        raise NpzError(f"{out} holds {', '.join(map(str, stale))} of an earlier export, which "
                       "this one would not replace (gns would read them with it): remove "
                       "them or write to another directory")
    written, scenes = {}, {s: {} for s in SPLITS}
    for rel, group in groups.items():
        ours_here = {**ours, "scenes": _write_npz(out / rel, group, Path(dataset), material)}
        if by_purpose:
            theirs = {p: {**_section_of([(s, t) for s, t in group if (s == "test") == test],
                                        base), **carried[p]}
                      for p, test in (("train", False), ("rollout", True))}
        else:
            theirs = {**_section_of(group, base), **carried["train"]}
        theirs["minority"] = ours_here
        (out / rel / "metadata.json").write_text(json.dumps(theirs, indent=1))
        written[rel] = theirs
        for s, named in ours_here["scenes"].items():
            scenes[s].update(named)
    return {"datasets": written, "dt": base["dt"],
            "default_connectivity_radius": base["default_connectivity_radius"],
            "minority": {"scenes": scenes}}


def _stale(out: Path, groups: dict) -> list[Path]:
    """Files of their layout under out that writing `groups` would leave as they are."""
    keep = {out / rel / f"{s}.npz" for rel, group in groups.items() for s, _ in group}
    keep |= {out / rel / "metadata.json" for rel in groups}
    dirs = [out, *sorted(out.glob("domain_*"))]
    return [f for d in dirs for f in [d / "metadata.json", *(d / f"{s}.npz" for s in SPLITS)]
            if f.exists() and f not in keep]


def _bounds_key(t) -> tuple:
    return tuple(float(v) for v in np.asarray(t.bounds_m).ravel())


def _section_of(members: list, base: dict) -> dict:
    """Their metadata for trajectories [(split, Trajectory)] that share bounds."""
    frames = {t.positions.shape[0] for _, t in members}
    return {"bounds": np.asarray(members[0][1].bounds_m).tolist(),
            # their rollout compares sequence_length - 6 predicted frames with positions[6:]
            "sequence_length": frames.pop() if len(frames) == 1 else None, **base}


def _write_npz(where: Path, members: list, dataset: Path, material: str) -> dict:
    """{split}.npz at `where` for trajectories [(split, Trajectory)]; returns the scenes
    {split: {name: {bounds_m, friction_angle_deg}}} that import reads back."""
    entries, scenes = {s: {} for s in SPLITS}, {s: {} for s in SPLITS}
    for split, t in members:
        ptype = _particle_type(dataset, split, t.name, t.positions.shape[1])
        phi = t.friction_angle_deg
        value = [t.positions.astype(np.float32), ptype]
        if material != "none":
            value.append(np.float64(math.tan(math.radians(phi)) if material == "tan_phi"
                                    else phi))
        entries[split][t.name] = np.empty(len(value), dtype=object)
        entries[split][t.name][:] = value
        scenes[split][t.name] = {"bounds_m": t.bounds_m.tolist(), "friction_angle_deg": phi}
    where.mkdir(parents=True, exist_ok=True)
    for split, named in entries.items():
        if named:
            np.savez_compressed(where / f"{split}.npz", **named)
    return scenes


def _particle_type(dataset: Path, split: str, name: str, n: int) -> np.ndarray:
    """A scene's stored particle types [n] int64 (sand where the dataset has none)."""
    import h5py

    with h5py.File(dataset / f"{split}.h5", "r") as f:
        g = f[name]
        if "particle_type" in g:
            return g["particle_type"][...].astype(np.int64)
    return np.full(n, PARTICLE_TYPE_SAND, np.int64)

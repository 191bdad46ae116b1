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

Their loader unpickles the object arrays; ours reads them with an unpickler that builds
numpy arrays and nothing else, so a file cannot run code here. Export writes what their
loader reads, plus a "minority" section in metadata.json (per-scene bounds and friction,
spacing) that import reads back.
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


def _metadata(src: Path) -> dict:
    try:
        meta = json.loads((src / "metadata.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise NpzError(f"{src}: cannot read metadata.json ({exc})") from None
    if not isinstance(meta, dict):
        raise NpzError(f"{src}/metadata.json: expected a JSON object")
    if isinstance(meta.get("train"), dict):  # split by purpose: train and rollout
        meta = {**meta["train"], "minority": meta.get("minority")}
    return meta


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
    """Their dataset directory src (train.npz, optional valid.npz / test.npz, metadata.json)
    -> our dataset at out_dir; material: how their material_property encodes the friction
    angle (MATERIAL_ENCODINGS). Positions are taken as m, dt as the frame interval (s) unless
    frame_interval_s is given. Returns our metadata."""
    src, log = Path(src), sys.stderr if log is None else log
    if material not in MATERIAL_ENCODINGS:
        raise NpzError(f"material {material!r}, expected one of {', '.join(MATERIAL_ENCODINGS)}")
    meta = _metadata(src)
    if int(meta.get("dim", 3)) != 3:
        raise NpzError(f"{src}: dim {meta.get('dim')}; the minority GNS is 3D")
    dt = frame_interval_s if frame_interval_s is not None else meta.get("dt")
    if dt is None or not math.isfinite(float(dt)) or float(dt) <= 0:
        raise NpzError(f"{src}: metadata.json dt {dt!r} is not a frame interval > 0 (s): give "
                       "one (--frame-interval)")
    radius = connectivity_radius_m or meta.get("default_connectivity_radius")
    if radius is None or not float(radius) > 0:
        raise NpzError(f"{src}: no default_connectivity_radius in metadata.json: give one "
                       "(--radius)")
    splits = [s for s in SPLITS if (src / f"{s}.npz").is_file()]
    if "train" not in splits:
        raise NpzError(f"{src}: no train.npz")
    splits_data = {s: load_npz(src / f"{s}.npz") for s in splits}  # all checked before writing

    def items():
        for split, trajs in splits_data.items():
            for name, item in trajs.items():
                where = str(src / f"{split}.npz")
                run = _run(name, split, item, meta, where, material=material,
                           frame_interval_s=float(dt))
                p = to_packed(run, Path(where), split, friction_deg)
                p.scene["source"] = f"{where}:{name}"
                yield p

    return pack(items(), out_dir, connectivity_radius_m=float(radius), log=log,
                spacing_rtol=0.05, meta={"config": "", "imported_from": str(src)})


def export_npz(dataset: str | Path, out_dir: str | Path, *, material: str = "tan_phi") -> dict:
    """Our dataset -> their layout at out_dir: {split}.npz per split with trajectories (one
    entry per scene: positions [T, n, 3] float32 m, particle_type [n] int64, and unless
    material is "none" the friction angle as tan(phi) or in degrees) and metadata.json.
    Returns the metadata written."""
    if material not in MATERIAL_ENCODINGS:
        raise NpzError(f"material {material!r}, expected one of {', '.join(MATERIAL_ENCODINGS)}")
    meta = load_metadata(dataset)
    out = Path(out_dir)
    scenes, frames = {s: {} for s in SPLITS}, []
    written = {}
    for split in SPLITS:
        try:
            trajs = load_split(dataset, split)
        except OSError as exc:
            raise NpzError(f"{dataset}: cannot read the {split} split ({exc})") from None
        entries = {}
        for t in trajs:
            ptype = _particle_type(Path(dataset), split, t.name, t.positions.shape[1])
            phi = t.friction_angle_deg
            value = [t.positions.astype(np.float32), ptype]
            if material != "none":
                value.append(np.float64(math.tan(math.radians(phi)) if material == "tan_phi"
                                        else phi))
            entries[t.name] = np.empty(len(value), dtype=object)
            entries[t.name][:] = value
            scenes[split][t.name] = {"bounds_m": t.bounds_m.tolist(), "friction_angle_deg": phi}
            frames.append(t.positions.shape[0])
        written[split] = entries
    out.mkdir(parents=True, exist_ok=True)
    for split, entries in written.items():
        if entries:
            np.savez_compressed(out / f"{split}.npz", **entries)
    features = 0 if material == "none" else 1
    theirs = {
        "bounds": meta["bounds_m"], "sequence_length": min(frames) - 1,
        "default_connectivity_radius": meta["connectivity_radius_m"], "dim": 3,
        "dt": meta["frame_interval_s"],
        **{k: meta[k] for k in ("vel_mean", "vel_std", "acc_mean", "acc_std")},
        "nnode_in": NNODE_IN_3D + features, "nedge_in": NEDGE_IN_3D,
        **({"material_feature_len": features} if features else {}),
        "minority": {"format": meta["format"], "material": material,
                     "particle_spacing_m": meta["particle_spacing_m"],
                     "friction_mean_deg": meta["friction_mean_deg"],
                     "friction_std_deg": meta["friction_std_deg"], "scenes": scenes,
                     "units": {"positions": "m", "dt": "s", "velocity": "m/frame",
                               "acceleration": "m/frame^2", "bounds": "m"}},
    }
    (out / "metadata.json").write_text(json.dumps(theirs, indent=1))
    return theirs


def _particle_type(dataset: Path, split: str, name: str, n: int) -> np.ndarray:
    """A scene's stored particle types [n] int64 (sand where the dataset has none)."""
    import h5py

    with h5py.File(dataset / f"{split}.h5", "r") as f:
        g = f[name]
        if "particle_type" in g:
            return g["particle_type"][...].astype(np.int64)
    return np.full(n, PARTICLE_TYPE_SAND, np.int64)

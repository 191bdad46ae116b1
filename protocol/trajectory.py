"""HDF5 trajectories: the one layout that `minority sim` writes, GNS rollouts write, and the
GNS dataset, the oracle and the preview read.

Datasets (frames grow along axis 0, one chunk per frame):

    positions      [frames, n, 3] float32, m
    velocities     [frames, n, 3] float32, m/s
    displacements  [frames, n, 3] float32, m (from the frame-0 position)
    time           [frames] float64, s; written last, so len(time) is the number of
                   complete frames of a file whose writer was killed

An MPM run (format SIM_FORMAT, sim.output) adds

    step           [frames] int64, MPM steps taken
    kinetic_energy [frames] float64, J
    momentum       [frames, 3] float64, kg m/s
    particle_type  [n] int32 (PARTICLE_TYPE_SAND)
    material       [n] float32, friction angle in degrees
    attrs: output_interval_s (s, the frame interval), dt_s, dt_mode, bounds_m [3, 2] (m),
           particle_spacing_m, cell_size_m, scene_name, scene_toml, material_table (JSON),
           and from `minority sim` ranks, rebalance_every

A GNS rollout (format ROLLOUT_FORMAT, gns.export) has the frame datasets only; its velocities
are backward differences; attrs frame_interval_s (s) and the caller's (bounds_m,
particle_spacing_m, scene, checkpoint, ...; dicts and lists as JSON).

Both: attrs format, units (JSON: the unit of every dataset and attr above), n_particles.

Any simulator's run (read_trajectory; the GNS dataset builder's `--from-runs`): a plain HDF5
file that needs only

    positions      [frames, n, 3] float, m (z up: the model's gravity axis)
    attr frame_interval_s   s between frames (an MPM run's output_interval_s is read as it;
                            without either, a `time` dataset of uniform steps gives it)
    attr bounds_m  [3, 2] float, m: lo, hi per axis of the domain; its faces are the walls
                   the GNS sees (node features: distance to each face)

and may add

    time           [frames] float64, s; when present, len(time) frames are complete
    particle_type  [n] int, the GNS's particle types: PARTICLE_TYPE_SAND (6, the default)
                   for material the model moves, PARTICLE_TYPE_KINEMATIC (3) for boundary
                   particles the simulator moves (the dataset leaves them out: walls are
                   bounds_m)
    material       [n] float, friction angle in degrees: the model's material feature, one
                   value per run
    attr particle_spacing_m  m, the seeding spacing (rollouts seed new scenes at it);
                   estimated from frame 0 when absent
    attr scene_name (or name)  the run's name (default: the file's stem)

Every other dataset and attr is ignored. A `minority sim` run is such a file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

SIM_FORMAT = "minority-sim-trajectory/1"
ROLLOUT_FORMAT = "minority-gns-rollout/1"
FORMATS = (SIM_FORMAT, ROLLOUT_FORMAT)
PARTICLE_TYPE_SAND = 6  # the id GNS (learning_to_simulate lineage) uses for sand
PARTICLE_TYPE_KINEMATIC = 3  # GNS: a particle moved by the simulator (a boundary), not the model
FRAME_FIELDS = ("positions", "velocities", "displacements")  # [frames, n, 3] float32
SIM_SERIES = {"step": ((), "i8"), "kinetic_energy": ((), "f8"), "momentum": ((3,), "f8")}
UNITS = {
    "positions": "m", "velocities": "m/s", "displacements": "m", "time": "s",
    "kinetic_energy": "J", "momentum": "kg m/s", "material": "deg (friction angle)",
    "bounds_m": "m", "particle_spacing_m": "m", "cell_size_m": "m", "dt_s": "s",
    "output_interval_s": "s", "step": "1", "particle_type": "1",
}
ROLLOUT_UNITS = {"positions": "m", "velocities": "m/s", "displacements": "m", "time": "s"}
SERIES_CHUNK = 1024  # frames per chunk of the per-frame scalars


class TrajectoryError(ValueError):
    """A file that is not a readable trajectory of the expected format."""


class FrameWriter:
    """Append frames to a new trajectory file in SWMR mode, flushed after each frame, so a
    killed writer leaves a readable file with every complete frame. Use as a context manager.

    n: particles. attrs: the file's attributes besides format, units and n_particles (dicts
    and lists are written as JSON). particle_data: [n] arrays written once (e.g. material).
    series: extra per-frame datasets, name -> (shape after the frame axis, dtype)."""

    def __init__(self, path: str | Path, n: int, *, fmt: str, units: dict, attrs: dict,
                 particle_data: dict[str, np.ndarray] | None = None,
                 series: dict[str, tuple[tuple[int, ...], str]] | None = None) -> None:
        self.path, self.n, self.frames = Path(path), n, 0
        self.series = dict(series or {})
        self._f = f = h5py.File(self.path, "w", libver="latest")
        for name in FRAME_FIELDS:
            f.create_dataset(name, shape=(0, n, 3), maxshape=(None, n, 3), dtype="f4",
                             chunks=(1, n, 3))
        for name, (tail, dtype) in {**self.series, "time": ((), "f8")}.items():
            f.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype,
                             chunks=(SERIES_CHUNK, *tail))
        for name, data in (particle_data or {}).items():
            f.create_dataset(name, data=data)
        f.attrs["format"] = fmt
        f.attrs["units"] = json.dumps(units)
        f.attrs["n_particles"] = n
        for key, value in attrs.items():
            f.attrs[key] = json.dumps(value) if isinstance(value, dict | list) else value
        f.swmr_mode = True
        f.flush()

    def write_frame(self, time_s: float, fields: dict[str, np.ndarray], **series) -> None:
        """Append one frame: fields holds [n, 3] arrays named as FRAME_FIELDS (m, m/s, m),
        series a value of each extra per-frame dataset; time_s (s) is written last."""
        self.write_frames(np.array([time_s]), {k: v[None] for k, v in fields.items()},
                          **{k: np.asarray(v)[None] for k, v in series.items()})

    def write_frames(self, times_s: np.ndarray, fields: dict[str, np.ndarray],
                     **series) -> None:
        """Append frames at once: times_s [frames] (s), fields [frames, n, 3] arrays named as
        FRAME_FIELDS, series [frames, ...] per extra dataset; times are written last."""
        f, k, m = self._f, self.frames, len(times_s)
        for name in FRAME_FIELDS:
            ds = f[name]
            ds.resize(k + m, axis=0)
            ds[k:] = fields[name].astype(np.float32)
        for name, values in [*((s, series[s]) for s in self.series), ("time", times_s)]:
            ds = f[name]
            ds.resize(k + m, axis=0)
            ds[k:] = values
        f.flush()
        self.frames = k + m

    def close(self) -> None:
        if self._f.id.valid:
            self._f.close()

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_rollout(path: str | Path, positions: np.ndarray, velocities: np.ndarray,
                  frame_interval_s: float, *, attrs: dict) -> Path:
    """A rollout file: positions [frames, n, 3] (m), velocities [frames, n, 3] (m/s), frames
    every frame_interval_s (s) from t = 0; displacements from frame 0."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames, n, _ = positions.shape
    with FrameWriter(path, n, fmt=ROLLOUT_FORMAT, units=ROLLOUT_UNITS,
                     attrs={"frame_interval_s": frame_interval_s, **attrs}) as w:
        w.write_frames(np.arange(frames) * frame_interval_s, {
            "positions": positions, "velocities": velocities,
            "displacements": positions - positions[0]})
    return path


def open_trajectory(path: str | Path) -> h5py.File:
    """Open a trajectory for reading, also one whose writer was killed (SWMR read; a plain
    h5py.File(path, 'r') refuses such a file as 'already open for write')."""
    return h5py.File(path, "r", swmr=True)


def complete_frames(f: h5py.File) -> int:
    """Frames of an open trajectory that were written to the end (len(time); a file
    without `time` counts its positions)."""
    return len(f["time"]) if "time" in f else len(f["positions"])


def frames_written(path: str | Path) -> int:
    """Complete frames of the trajectory at path; 0 if it is missing or unreadable."""
    try:
        with open_trajectory(path) as f:
            return complete_frames(f)
    except (OSError, KeyError):
        return 0


def attribute(value):
    """An HDF5 attribute: JSON objects and lists decoded, other text (e.g. a scene's TOML,
    which may start with "[domain]") as it is."""
    if isinstance(value, str) and value[:1] in ("[", "{"):
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value


def frame_interval_s(attrs) -> float:
    """The time between frames (s) of either format."""
    if attrs.get("format") == SIM_FORMAT:
        return float(attrs["output_interval_s"])
    return float(attrs["frame_interval_s"])


def read_sim(path: str | Path, stride: int = 1) -> tuple[np.ndarray, dict]:
    """An MPM run's complete frames: positions of every stride-th frame [frames, n, 3]
    float32 (m), and the attrs output_interval_s (s), bounds_m [3, 2] (m),
    particle_spacing_m (m), scene_name and friction_angle_deg (of particle 0, deg)."""
    with open_trajectory(path) as f:
        pos = f["positions"][:complete_frames(f):stride]
        attrs = {k: f.attrs[k] for k in ("output_interval_s", "bounds_m",
                                         "particle_spacing_m", "scene_name")}
        attrs["friction_angle_deg"] = float(f["material"][0])
    return pos, attrs


def read_rollout(path: str | Path) -> dict:
    """A rollout, or an MPM run's trajectory read as one: positions [frames, n, 3] (m) of the
    complete frames, frame_interval_s (s), bounds_m [3, 2] (m), and every other attribute
    (JSON decoded), checked. Raises TrajectoryError."""
    try:
        with open_trajectory(path) as f:
            fmt = f.attrs.get("format")
            if fmt not in FORMATS:
                raise TrajectoryError(f"{path}: not a rollout (format {fmt!r}, expected "
                                      f"{ROLLOUT_FORMAT!r} or an MPM run's {SIM_FORMAT!r})")
            out = {k: attribute(v) for k, v in f.attrs.items()}
            out["positions"] = f["positions"][:complete_frames(f)]
            out["frame_interval_s"] = frame_interval_s(out)
    except (OSError, KeyError) as exc:
        raise TrajectoryError(f"{path}: cannot read the rollout ({exc})") from None
    pos = out["positions"]
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 3 or not np.isfinite(pos).all():
        raise TrajectoryError(f"{path}: positions must be finite [frames >= 3, n, 3], got "
                              f"{list(pos.shape)}")
    try:
        out["bounds_m"] = np.asarray(out["bounds_m"], dtype=np.float64).reshape(3, 2)
    except (KeyError, ValueError) as exc:
        raise TrajectoryError(f"{path}: bounds_m must be [3, 2] lo, hi per axis (m): "
                              f"{exc!r}") from None
    return out


@dataclass
class RunTrajectory:
    """A run of any simulator (the layout in this module's docstring), checked."""

    name: str
    positions: np.ndarray  # [frames, n, 3] float32, m: every stride-th complete frame
    frame_interval_s: float  # s between the frames of `positions` (stride included)
    bounds_m: np.ndarray  # [3, 2] float64, m: lo, hi per axis
    particle_type: np.ndarray  # [n] int32 (PARTICLE_TYPE_SAND where the file has none)
    material: np.ndarray | None  # [n] float32, friction angle in degrees; None: absent
    particle_spacing_m: float | None  # m; None: absent
    attrs: dict = field(default_factory=dict)  # every attribute of the file, JSON decoded


def _run_frame_interval(f: h5py.File, frames: int) -> float:
    for key in ("frame_interval_s", "output_interval_s"):
        if key in f.attrs:
            return float(np.asarray(f.attrs[key]).reshape(()))
    if "time" in f and frames >= 2:
        steps = np.diff(np.asarray(f["time"][:frames], dtype=np.float64))
        if np.allclose(steps, steps[0], rtol=1e-6, atol=0.0):
            return float(steps[0])
        raise TrajectoryError("time is not uniformly spaced; add attr frame_interval_s (s)")
    raise TrajectoryError("no frame interval: add attr frame_interval_s (s between frames)")


def _per_particle(f: h5py.File, name: str, n: int, kind: str) -> np.ndarray | None:
    if name not in f:
        return None
    data = np.asarray(f[name][...])
    if data.shape != (n,) or data.dtype.kind not in kind:
        raise TrajectoryError(f"{name} must be [n] = [{n}] {'int' if kind == 'iu' else 'float'}"
                              f", got {list(data.shape)} {data.dtype}")
    return data


def read_trajectory(path: str | Path, stride: int = 1) -> RunTrajectory:
    """A run of any simulator in the layout of this module's docstring: every stride-th
    complete frame and the particle data, checked. Raises TrajectoryError naming the file and
    what is missing or malformed."""
    path = Path(path)
    if stride < 1:
        raise TrajectoryError(f"{path}: stride {stride} must be >= 1")
    try:
        with open_trajectory(path) as f:
            missing = [k for k in ("positions",) if k not in f] + [
                f"attr {k}" for k in ("bounds_m",) if k not in f.attrs]
            if missing:
                raise TrajectoryError(f"missing {', '.join(missing)} (required: positions "
                                      "[frames, n, 3] m, attr bounds_m [3, 2] m, attr "
                                      "frame_interval_s s)")
            ds = f["positions"]
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 3 or ds.shape[2] != 3 \
                    or ds.dtype.kind != "f":
                raise TrajectoryError(f"positions must be a float dataset [frames, n, 3] (m), "
                                      f"got {getattr(ds, 'shape', 'a group')}")
            frames = min(complete_frames(f), ds.shape[0])
            n = ds.shape[1]
            if frames < 2 or n < 1:
                raise TrajectoryError(f"positions hold {frames} complete frames of {n} "
                                      "particles; at least 2 frames of 1 particle are needed")
            dt = _run_frame_interval(f, frames)
            pos = ds[:frames:stride].astype(np.float32)
            ptype = _per_particle(f, "particle_type", n, "iu")
            material = _per_particle(f, "material", n, "fiu")
            attrs = {k: attribute(v) for k, v in f.attrs.items()}
    except TrajectoryError as exc:
        raise TrajectoryError(f"{path}: {exc}") from None
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise TrajectoryError(f"{path}: cannot read the trajectory ({exc})") from None
    if not np.isfinite(dt) or dt <= 0:
        raise TrajectoryError(f"{path}: frame interval {dt} s must be finite and > 0")
    try:
        bounds = np.asarray(attrs["bounds_m"], dtype=np.float64).reshape(3, 2)
    except (ValueError, TypeError) as exc:
        raise TrajectoryError(f"{path}: bounds_m must be [3, 2] lo, hi per axis (m): "
                              f"{exc}") from None
    if not np.isfinite(bounds).all() or (bounds[:, 1] <= bounds[:, 0]).any():
        raise TrajectoryError(f"{path}: bounds_m {bounds.tolist()} must be finite with lo < hi "
                              "on every axis (m)")
    if not np.isfinite(pos).all():
        bad = int(np.argmax(~np.isfinite(pos).all(axis=(1, 2)))) * stride
        raise TrajectoryError(f"{path}: non-finite positions (first in frame {bad})")
    if material is not None and not np.isfinite(material).all():
        raise TrajectoryError(f"{path}: non-finite material (friction angle, deg)")
    spacing = attrs.get("particle_spacing_m")
    if spacing is not None:
        spacing = float(np.asarray(spacing).reshape(()))
        if not np.isfinite(spacing) or spacing <= 0:
            raise TrajectoryError(f"{path}: particle_spacing_m {spacing} must be > 0 (m)")
    name = str(attrs.get("scene_name") or attrs.get("name") or path.stem)
    return RunTrajectory(
        name, pos, dt * stride, bounds,
        np.full(n, PARTICLE_TYPE_SAND, np.int32) if ptype is None else ptype.astype(np.int32),
        None if material is None else material.astype(np.float32), spacing, attrs)

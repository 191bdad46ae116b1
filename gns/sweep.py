"""The MPM sweep behind the GNS dataset: its config and the scenes it plans (geometry and
friction drawn per split, deterministic in the config's seed). minority.sweep runs them."""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from minority.gns.dataset import COARSE_GRAIN_METHODS

SPLITS = ("train", "valid", "test")
MAX_DRAWS = 100_000  # rejection-sampling attempts before the config is declared infeasible


class SweepError(ValueError):
    """A sweep config that cannot be planned or a run that failed."""


@dataclass(frozen=True)
class ScenePlan:
    name: str
    split: str
    length_m: float  # L0
    width_m: float  # channel width = column width
    height_m: float  # H0
    friction_angle_deg: float
    domain_length_m: float
    particles: int

    @property
    def aspect_ratio(self) -> float:
        return self.height_m / self.length_m


@dataclass
class SweepConfig:
    path: Path
    seed: int
    duration_s: float
    output_interval_s: float
    stride: int
    connectivity_radius_m: float
    geometry: dict
    splits: dict
    named: list[dict] = field(default_factory=list)
    # [[extra]]: {split, count, geometry overrides}, drawn after every other random scene
    extra: list[dict] = field(default_factory=list)
    # the MPM runs at a cell coarse_grain times smaller (coarse_grain^3 times the particles);
    # the dataset makes each group of coarse_grain^3 particles one at the spacing, by the
    # group's mean or by one sampled member (gns.dataset.coarse_grain)
    coarse_grain: int = 1
    coarse_grain_method: str = "mean"

    @property
    def spacing_m(self) -> float:
        return float(self.geometry["particle_spacing_m"])


def _read(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """The config's tables; `extends = "base.toml"` starts from that file's (relative to this
    one), each table of this file updating the base's key by key, `[[extra]]` appended."""
    raw = tomllib.loads(path.read_text())
    base_name = raw.pop("extends", None)
    if base_name is None:
        return raw
    if path.resolve() in seen:
        raise SweepError(f"{path}: `extends` loops back to it")
    base = _read(path.parent / base_name, seen + (path.resolve(),))
    for key, value in raw.items():
        if key == "extra":
            base["extra"] = list(base.get("extra", [])) + list(value)
        elif isinstance(value, dict) and isinstance(base.get(key), dict):
            base[key] = {**base[key], **value}
        else:
            base[key] = value
    return base


def load_config(path: str | Path) -> SweepConfig:
    path = Path(path)
    try:
        raw = _read(path)
        cfg = SweepConfig(path=path, seed=int(raw["seed"]),
                          duration_s=float(raw["duration_s"]),
                          output_interval_s=float(raw["output_interval_s"]),
                          stride=int(raw["stride"]),
                          connectivity_radius_m=float(raw["connectivity_radius_m"]),
                          geometry=raw["geometry"], splits=raw["splits"],
                          named=list(raw.get("named", [])),
                          extra=list(raw.get("extra", [])),
                          coarse_grain=int(raw.get("coarse_grain", 1)),
                          coarse_grain_method=str(raw.get("coarse_grain_method", "mean")))
    except KeyError as exc:
        raise SweepError(f"{path}: missing key {exc}") from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise SweepError(f"{path}: {exc}") from None
    if cfg.stride < 1 or cfg.connectivity_radius_m <= 0 or cfg.coarse_grain < 1:
        raise SweepError(f"{path}: stride and coarse_grain must be >= 1 and "
                         "connectivity_radius_m > 0")
    if cfg.coarse_grain_method not in COARSE_GRAIN_METHODS:
        raise SweepError(f"{path}: coarse_grain_method {cfg.coarse_grain_method!r}, expected "
                         f"one of {', '.join(COARSE_GRAIN_METHODS)}")
    # one resolution per sweep: scene_toml and the dataset use the [geometry] cell and spacing
    ranges = set(cfg.geometry) - {"particle_spacing_m", "cell_size_m"}
    for i, ex in enumerate(cfg.extra):
        count = ex.get("count")
        if ex.get("split") not in ("train", "valid") or type(count) is not int or count < 1:
            raise SweepError(f"{path}: [[extra]] {i + 1} needs split = \"train\" or \"valid\" "
                             "and an integer count >= 1")
        unknown = set(ex) - {"split", "count"} - ranges
        if unknown:
            raise SweepError(f"{path}: [[extra]] {i + 1}: {sorted(unknown)} are not [geometry] "
                             "ranges it may override")
    return cfg


def _in_bands(x: float, bands: list) -> bool:
    return any(lo <= x <= hi for lo, hi in bands)


def _count(length: float, width: float, height: float, s: float) -> int:
    return round(length / s) * round(width / s) * round(height / s)


def _draw(cfg: SweepConfig, rng: np.random.Generator, plans: list[ScenePlan], split: str,
          want: int, g: dict) -> None:
    """Append `split` scenes drawn from the ranges of geometry `g` until there are `want`."""
    s, cell, sp = cfg.spacing_m, float(g["cell_size_m"]), cfg.splits
    held_a, held_phi = sp["held_out_aspect_ratio"], sp["held_out_friction_angle_deg"]
    draws = 0
    while sum(p.split == split for p in plans) < want:
        draws += 1
        if draws > MAX_DRAWS:
            raise SweepError(f"{cfg.path}: cannot draw {want} {split} scenes within the "
                             "geometry bounds; widen the ranges")
        length = round(rng.uniform(*g["length_m"]) / s) * s
        width = round(rng.uniform(*g["width_m"]) / cell) * cell
        a = rng.uniform(*g["aspect_ratio"])
        height = min(round(a * length / s) * s, float(g["max_height_m"]))
        phi = round(float(rng.uniform(*g["friction_angle_deg"])), 2)
        if split == "test":  # alternate: a held-out aspect ratio, a held-out friction
            if sum(p.split == "test" for p in plans) % 2 == 0:
                a = rng.uniform(*held_a[0])
            else:
                phi = round(float(rng.uniform(*held_phi[0])), 2)
            height = min(round(a * length / s) * s, float(g["max_height_m"]))
        a_real = height / length
        held = _in_bands(a_real, held_a) or _in_bands(phi, held_phi)
        if held != (split == "test"):
            continue
        n = _count(length, width, height, s)
        if not g["particles"][0] <= n <= g["particles"][1]:
            continue
        i = sum(p.split == split for p in plans)
        plans.append(ScenePlan(f"{split}_{i:03d}", split, round(length, 6), round(width, 6),
                               round(height, 6), phi, float(g["domain_length_m"]), n))


def plan(cfg: SweepConfig) -> list[ScenePlan]:
    """Scenes of every split, deterministic in the config's seed."""
    sp = cfg.splits
    rng = np.random.default_rng(cfg.seed)
    plans: list[ScenePlan] = []
    # extra_train / extra_valid, then the [[extra]] tables, are drawn after the test scenes
    # from the same stream, so that enlarging a sweep keeps every scene it had (and its runs)
    rounds = [(name, int(sp[name]), {}) for name in SPLITS] + [
        ("train", int(sp["train"]) + int(sp.get("extra_train", 0)), {}),
        ("valid", int(sp["valid"]) + int(sp.get("extra_valid", 0)), {})]
    for ex in cfg.extra:
        split = ex["split"]
        have = max(w for name, w, _ in rounds if name == split)
        rounds.append((split, have + ex["count"],
                       {k: v for k, v in ex.items() if k not in ("split", "count")}))
    for split, want, overrides in rounds:
        _draw(cfg, rng, plans, split, want, {**cfg.geometry, **overrides})
    g, s = cfg.geometry, cfg.spacing_m
    for named in cfg.named:
        plans.append(ScenePlan(
            named["name"], "test", float(named["length_m"]), float(named["width_m"]),
            float(named["height_m"]), float(named["friction_angle_deg"]),
            float(named.get("domain_length_m", g["domain_length_m"])),
            _count(named["length_m"], named["width_m"], named["height_m"], s)))
    return plans


def plans_table(plans: list[ScenePlan]) -> list[dict]:
    return [asdict(p) | {"aspect_ratio": round(p.aspect_ratio, 4)} for p in plans]

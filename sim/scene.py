"""Scene description: typed dataclasses loaded from a TOML file.

A scene fixes the domain (an axis-aligned box from the origin, SI units), the background
grid cell size, the bodies of sand (boxes and cylinders seeded on a regular lattice), the
material, the boundary friction, gravity and the time span. All keys and their units are
documented in sim/README.md; `load_scene` rejects unknown or bad keys with a `SceneError`
that names the key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from enum import Enum
from importlib import resources
from pathlib import Path

# the shipped scene files: package data, installed as files wherever the package is
SCENES_DIR = Path(str(resources.files("minority.sim").joinpath("scenes")))
AXES = ("x", "y", "z")
FACES = ("x_min", "x_max", "y_min", "y_max", "z_min", "z_max")
DEFAULT_CFL = 0.3
MAX_CFL = 0.5  # beyond this the explicit MLS-MPM update is not stable in our tests
DEFAULT_GRAVITY_M_S2 = (0.0, 0.0, -9.81)
DEFAULT_FACE_FRICTION = 0.0
MAX_PARTICLES_PER_CELL_PER_AXIS = 8
# What one process may be asked to allocate, checked before anything is: a cell size typed
# 1e-5 instead of 1e-2 otherwise asks numpy for terabytes. column_1m, the largest shipped
# scene, has 720,000 cells and 1,036,800 particles.
MAX_GRID_CELLS = 50_000_000  # cells of the domain: 3.2 GB of grid at GRID_BYTES_PER_CELL
MAX_PARTICLES = 20_000_000  # seeded particles: 6.2 GB of state at PARTICLE_BYTES (and spares)
GRID_BYTES_PER_CELL = 64  # float64 x sim.kernels.GRID_FIELDS (8) per node; tests check it
PARTICLE_BYTES = 312  # float64 x 39 values of sim.state.ParticleState; tests check it
MAX_SCENE_FILE_BYTES = 1 << 20  # a scene is a page of TOML (the shipped ones: about 1 kB)


class SceneError(ValueError):
    """A scene file is invalid; the message names the offending key."""


class DPCone(Enum):
    """How the Drucker-Prager cone is fitted to the friction angle phi; M is the slope q / p
    of the cone in (p, q) space (see sim/README.md, "Drucker-Prager cone").

    SIMPLE_SHEAR (default): M = sqrt(3) tan(phi), i.e. sqrt(J2) <= tan(phi) p: a layer in
    simple shear yields at shear / normal stress = tan(phi), the granular friction
    coefficient of the mu(I) rheology (GDR MiDi 2004, Jop et al. 2006) and of a pile at its
    angle of repose. PLANE_STRAIN: M = sqrt(3) sin(phi), the Mohr-Coulomb angle phi in plane
    strain for this return mapping's non-dilatant flow (which then shears at tan = sin(phi),
    Davis 1968). COMPRESSION: Klár et al. 2016, M = 6 sin(phi) / (3 - sin(phi)) (outer cone,
    matches triaxial compression)."""

    SIMPLE_SHEAR = "simple_shear"
    PLANE_STRAIN = "plane_strain"
    COMPRESSION = "compression"


DEFAULT_DP_CONE = DPCone.SIMPLE_SHEAR
DEFAULT_FLIP = 0.99  # FLIP fraction of the particle velocity update (0: APIC alone)


class Shape(Enum):
    BOX = "box"
    CYLINDER = "cylinder"


@dataclass(frozen=True)
class Material:
    """Drucker–Prager sand (no cohesion), Hencky elasticity."""

    density_kg_m3: float
    youngs_modulus_pa: float
    poisson_ratio: float
    friction_angle_deg: float
    dp_cone: DPCone = DEFAULT_DP_CONE

    @property
    def shear_modulus_pa(self) -> float:
        return self.youngs_modulus_pa / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda_pa(self) -> float:
        nu = self.poisson_ratio
        return self.youngs_modulus_pa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def p_wave_speed_m_s(self) -> float:
        """c = sqrt((lambda + 2 mu) / rho), m/s."""
        modulus = self.lame_lambda_pa + 2.0 * self.shear_modulus_pa
        return math.sqrt(modulus / self.density_kg_m3)

    @property
    def dp_slope_m(self) -> float:
        """Cone slope M = q / p (q = sqrt(3/2) |dev tau|, p = -tr(tau) / 3) for dp_cone."""
        phi = math.radians(self.friction_angle_deg)
        if self.dp_cone is DPCone.SIMPLE_SHEAR:
            return math.sqrt(3.0) * math.tan(phi)
        if self.dp_cone is DPCone.COMPRESSION:
            return 6.0 * math.sin(phi) / (3.0 - math.sin(phi))
        return math.sqrt(3.0) * math.sin(phi)

    @property
    def dp_alpha(self) -> float:
        """Klár et al. 2016 alpha of the yield |dev eps| + (3 lam + 2 mu)/(2 mu) tr(eps) alpha
        <= 0, i.e. |dev tau| <= 3 alpha p: alpha = M / (3 sqrt(3/2)). For COMPRESSION this
        is Klár's sqrt(2/3) * 2 sin(phi) / (3 - sin(phi))."""
        return self.dp_slope_m / (3.0 * math.sqrt(1.5))


@dataclass(frozen=True)
class Body:
    """A region filled with material points. Box: lo/hi corners (m). Cylinder: vertical
    axis through center_m (x, y), base at center_m z, radius_m and height_m."""

    shape: Shape
    lo_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hi_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    center_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius_m: float = 0.0
    height_m: float = 0.0
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Wall:
    """Interior half-space wall: nodes with side * (x[axis] - position_m) <= 0 inside the
    extent box lo_m..hi_m are solid; `side` (+1 or -1) points into the free region."""

    axis: int
    position_m: float
    side: int
    friction: float
    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]


@dataclass(frozen=True)
class Scene:
    name: str
    size_m: tuple[float, float, float]
    cell_size_m: float
    particles_per_cell_per_axis: int
    material: Material
    bodies: tuple[Body, ...]
    face_friction: dict[str, float]
    walls: tuple[Wall, ...]
    gravity_m_s2: tuple[float, float, float]
    duration_s: float
    output_interval_s: float
    cfl: float
    flip: float = DEFAULT_FLIP
    toml_text: str = field(default="", repr=False)

    @property
    def particle_spacing_m(self) -> float:
        return self.cell_size_m / self.particles_per_cell_per_axis

    @property
    def grid_cells(self) -> tuple[int, int, int]:
        return tuple(int(round(s / self.cell_size_m)) for s in self.size_m)


def _get(table: dict, key: str, where: str, kind, default=None, required=True):
    """Fetch table[key] as `kind` ('float', 'int', 'str', 'vec3'); SceneError names key."""
    name = f"{where}.{key}" if where else key
    if key not in table:
        if required and default is None:
            raise SceneError(f"missing key '{name}'")
        return default
    value = table[key]
    try:
        if kind == "vec3":
            if isinstance(value, str | dict) or len(value) != 3:
                raise TypeError
            out = tuple(float(v) for v in value)
        elif kind == "float":
            if isinstance(value, bool):
                raise TypeError
            out = float(value)
        elif kind == "int":
            if isinstance(value, bool) or int(value) != value:
                raise TypeError
            out = int(value)
        else:
            if not isinstance(value, str):
                raise TypeError
            out = value
    except (TypeError, ValueError, OverflowError):
        raise SceneError(f"key '{name}' must be a {kind}, got {value!r}") from None
    if kind in ("float", "vec3"):
        values = out if kind == "vec3" else (out,)
        if not all(math.isfinite(v) for v in values):
            raise SceneError(f"key '{name}' must be finite, got {value!r}")
    return out


def _table(data: dict, key: str) -> dict:
    """An optional table ({} when absent) that must be a table when present."""
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise SceneError(f"'{key}' must be a table ([{key}]), got {value!r}")
    return value


def _tables(data: dict, key: str) -> list[dict]:
    """An optional array of tables ([] when absent), written [[key]]."""
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
        raise SceneError(f"'{key}' must be an array of tables ([[{key}]]), got {value!r}")
    return value


def _check_keys(table: dict, allowed: set[str], where: str) -> None:
    for key in table:
        if key not in allowed:
            name = f"{where}.{key}" if where else key
            raise SceneError(f"unknown key '{name}'")


def _positive(value: float, name: str) -> float:
    if not value > 0.0:
        raise SceneError(f"key '{name}' must be > 0, got {value}")
    return value


def _parse_material(t: dict) -> Material:
    _check_keys(
        t,
        {"density_kg_m3", "youngs_modulus_pa", "poisson_ratio", "friction_angle_deg",
         "dp_cone"},
        "material",
    )
    cone = _get(t, "dp_cone", "material", "str", default=DEFAULT_DP_CONE.value)
    if cone not in {c.value for c in DPCone}:
        raise SceneError(f"key 'material.dp_cone' must be one of "
                         f"{[c.value for c in DPCone]}, got {cone!r}")
    m = Material(
        density_kg_m3=_positive(_get(t, "density_kg_m3", "material", "float"),
                                "material.density_kg_m3"),
        youngs_modulus_pa=_positive(_get(t, "youngs_modulus_pa", "material", "float"),
                                    "material.youngs_modulus_pa"),
        poisson_ratio=_get(t, "poisson_ratio", "material", "float"),
        friction_angle_deg=_get(t, "friction_angle_deg", "material", "float"),
        dp_cone=DPCone(cone),
    )
    if not 0.0 <= m.poisson_ratio < 0.5:
        raise SceneError(f"key 'material.poisson_ratio' must be in [0, 0.5), got {m.poisson_ratio}")
    if not 0.0 < m.friction_angle_deg < 90.0:
        raise SceneError(
            f"key 'material.friction_angle_deg' must be in (0, 90), got {m.friction_angle_deg}")
    return m


def _parse_body(t: dict, i: int, size_m) -> Body:
    where = f"body[{i}]"
    shape_name = _get(t, "shape", where, "str")
    try:
        shape = Shape(shape_name)
    except ValueError:
        raise SceneError(f"key '{where}.shape' must be 'box' or 'cylinder', "
                         f"got {shape_name!r}") from None
    velocity = _get(t, "velocity_m_s", where, "vec3", default=(0.0, 0.0, 0.0))
    if shape is Shape.BOX:
        _check_keys(t, {"shape", "lo_m", "hi_m", "velocity_m_s"}, where)
        lo = _get(t, "lo_m", where, "vec3")
        hi = _get(t, "hi_m", where, "vec3")
        for a in range(3):
            if not 0.0 <= lo[a] < hi[a] <= size_m[a] + 1e-12:
                raise SceneError(f"key '{where}.hi_m'/'lo_m' must satisfy 0 <= lo < hi <= "
                                 f"domain.size_m on axis {AXES[a]}")
        return Body(shape, lo_m=lo, hi_m=hi, velocity_m_s=velocity)
    _check_keys(t, {"shape", "center_m", "radius_m", "height_m", "velocity_m_s"}, where)
    center = _get(t, "center_m", where, "vec3")
    radius = _positive(_get(t, "radius_m", where, "float"), f"{where}.radius_m")
    height = _positive(_get(t, "height_m", where, "float"), f"{where}.height_m")
    inside = (center[0] - radius >= 0.0 and center[0] + radius <= size_m[0]
              and center[1] - radius >= 0.0 and center[1] + radius <= size_m[1]
              and center[2] >= 0.0 and center[2] + height <= size_m[2])
    if not inside:
        raise SceneError(f"key '{where}.center_m' puts the cylinder outside the domain")
    return Body(shape, center_m=center, radius_m=radius, height_m=height,
                velocity_m_s=velocity)


def _parse_wall(t: dict, i: int, size_m) -> Wall:
    where = f"wall[{i}]"
    _check_keys(t, {"axis", "position_m", "side", "friction", "lo_m", "hi_m"}, where)
    axis_name = _get(t, "axis", where, "str")
    if axis_name not in AXES:
        raise SceneError(f"key '{where}.axis' must be one of x, y, z, got {axis_name!r}")
    side_name = _get(t, "side", where, "str")
    if side_name not in ("+", "-"):
        raise SceneError(f"key '{where}.side' must be '+' or '-', got {side_name!r}")
    friction = _get(t, "friction", where, "float")
    if friction < 0.0:
        raise SceneError(f"key '{where}.friction' must be >= 0")
    return Wall(
        axis=AXES.index(axis_name),
        position_m=_get(t, "position_m", where, "float"),
        side=1 if side_name == "+" else -1,
        friction=friction,
        lo_m=_get(t, "lo_m", where, "vec3", default=(0.0, 0.0, 0.0)),
        hi_m=_get(t, "hi_m", where, "vec3", default=tuple(size_m)),
    )


def _count(x: float) -> str:
    return f"{x:,.0f}" if x < 1e15 else f"{x:.3g}"


def _bytes(b: float) -> str:
    """b bytes in decimal units (1 GB = 1e9 B), e.g. '164 TB'."""
    for unit, size in (("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if b >= size:
            return f"{b / size:.3g} {unit}"
    return f"{b:.0f} B"


def _check_grid_size(size_m: tuple[float, float, float], dx: float) -> None:
    """Refuse a grid of more than MAX_GRID_CELLS cells before the cell count is rounded or
    anything is allocated (size / dx may be past any integer, or infinite)."""
    per_axis = [s / dx for s in size_m]
    cells = math.prod(per_axis)
    if cells <= MAX_GRID_CELLS:
        return
    smallest_m = (math.prod(size_m) / MAX_GRID_CELLS) ** (1.0 / 3.0)
    shape = " x ".join(_count(c) for c in per_axis)
    asked = (f"{shape} = {_count(cells)} cells ({_bytes(cells * GRID_BYTES_PER_CELL)} at "
             f"{GRID_BYTES_PER_CELL} bytes per cell)" if math.isfinite(cells)
             else f"{shape} cells (more than 1e308)")
    raise SceneError(
        f"key 'domain.cell_size_m' = {dx:g} m makes a grid of {asked}, above the limit of "
        f"{MAX_GRID_CELLS:,} cells (MAX_GRID_CELLS in sim/scene.py); use a cell size of at least "
        f"{smallest_m * 1.001:.3g} m for domain.size_m = {list(size_m)}, or a smaller domain")


def _check_particle_count(bodies: tuple[Body, ...], dx: float, ppc: int) -> None:
    """Refuse bodies that would seed more than MAX_PARTICLES particles (estimated from their
    volumes at the lattice spacing dx / ppc) before the lattice is built."""
    spacing = dx / ppc
    count = 0.0
    for b in bodies:
        if b.shape is Shape.BOX:
            count += math.prod((h - lo) / spacing for lo, h in zip(b.lo_m, b.hi_m, strict=True))
        else:
            count += math.pi * b.radius_m**2 * b.height_m / spacing**3
    if count <= MAX_PARTICLES:
        return
    raise SceneError(
        f"the bodies would seed about {_count(count)} particles at a spacing of {spacing:g} m "
        f"(domain.cell_size_m {dx:g} m / particles.per_cell_per_axis {ppc}; "
        f"{_bytes(count * PARTICLE_BYTES)} at {PARTICLE_BYTES} bytes per particle), above the "
        f"limit of {MAX_PARTICLES:,} particles (MAX_PARTICLES in sim/scene.py); use a larger "
        f"cell size, fewer particles per cell or smaller bodies")


def parse_scene(data: dict, *, name: str = "scene", toml_text: str = "") -> Scene:
    """Build a Scene from a parsed TOML document."""
    _check_keys(data, {"name", "description", "domain", "material", "particles", "body",
                       "boundary", "wall", "time", "numerics", "gravity_m_s2"}, "")
    domain = data.get("domain")
    if not isinstance(domain, dict):
        raise SceneError("missing table 'domain'")
    _check_keys(domain, {"size_m", "cell_size_m"}, "domain")
    size_m = _get(domain, "size_m", "domain", "vec3")
    for a in range(3):
        _positive(size_m[a], f"domain.size_m[{a}]")
    dx = _positive(_get(domain, "cell_size_m", "domain", "float"), "domain.cell_size_m")
    _check_grid_size(size_m, dx)
    for a in range(3):
        cells = size_m[a] / dx
        if abs(cells - round(cells)) > 1e-6 * max(cells, 1.0) or round(cells) < 1:
            raise SceneError(f"key 'domain.size_m' must be a whole number of cells "
                             f"(domain.cell_size_m = {dx}) on axis {AXES[a]}")

    if not isinstance(data.get("material"), dict):
        raise SceneError("missing table 'material'")
    material = _parse_material(data["material"])

    particles = _table(data, "particles")
    _check_keys(particles, {"per_cell_per_axis"}, "particles")
    ppc = _get(particles, "per_cell_per_axis", "particles", "int", default=2)
    if not 1 <= ppc <= MAX_PARTICLES_PER_CELL_PER_AXIS:
        raise SceneError(f"key 'particles.per_cell_per_axis' must be in "
                         f"[1, {MAX_PARTICLES_PER_CELL_PER_AXIS}], got {ppc}")

    body_tables = _tables(data, "body")
    if not body_tables:
        raise SceneError("missing array of tables 'body' (use [[body]])")
    bodies = tuple(_parse_body(t, i, size_m) for i, t in enumerate(body_tables))
    _check_particle_count(bodies, dx, ppc)

    boundary = _table(data, "boundary")
    _check_keys(boundary, set(FACES) | {"friction"}, "boundary")
    base = _get(boundary, "friction", "boundary", "float", default=DEFAULT_FACE_FRICTION)
    face_friction = {}
    for face in FACES:
        mu = _get(boundary, face, "boundary", "float", default=base)
        if mu < 0.0:
            raise SceneError(f"key 'boundary.{face}' must be >= 0")
        face_friction[face] = mu
    walls = tuple(_parse_wall(t, i, size_m) for i, t in enumerate(_tables(data, "wall")))

    time = data.get("time")
    if not isinstance(time, dict):
        raise SceneError("missing table 'time'")
    _check_keys(time, {"duration_s", "output_interval_s", "cfl"}, "time")
    duration = _positive(_get(time, "duration_s", "time", "float"), "time.duration_s")
    interval = _positive(_get(time, "output_interval_s", "time", "float"),
                         "time.output_interval_s")
    cfl = _get(time, "cfl", "time", "float", default=DEFAULT_CFL)
    if not 0.0 < cfl <= MAX_CFL:
        raise SceneError(f"key 'time.cfl' must be in (0, {MAX_CFL}], got {cfl}")
    numerics = _table(data, "numerics")
    _check_keys(numerics, {"flip"}, "numerics")
    flip = _get(numerics, "flip", "numerics", "float", default=DEFAULT_FLIP)
    if not 0.0 <= flip <= 1.0:
        raise SceneError(f"key 'numerics.flip' must be in [0, 1], got {flip}")
    gravity = _get(data, "gravity_m_s2", "", "vec3", default=DEFAULT_GRAVITY_M_S2)
    return Scene(
        name=_get(data, "name", "", "str", default=name),
        size_m=size_m,
        cell_size_m=dx,
        particles_per_cell_per_axis=ppc,
        material=material,
        bodies=bodies,
        face_friction=face_friction,
        walls=walls,
        gravity_m_s2=gravity,
        duration_s=duration,
        output_interval_s=interval,
        cfl=cfl,
        flip=flip,
        toml_text=toml_text,
    )


def builtin_scene_path(name: str) -> Path:
    """Path of a shipped scene, e.g. builtin_scene_path("column_13k")."""
    path = SCENES_DIR / f"{name}.toml"
    if not path.is_file():
        known = sorted(p.stem for p in SCENES_DIR.glob("*.toml"))
        raise SceneError(f"no shipped scene {name!r}; known: {', '.join(known)}")
    return path


def scene_path(name_or_path: str | Path) -> Path:
    """A scene TOML path as given, or the shipped scene of that name when no such file
    exists and the name has no suffix (what every command's SCENE argument accepts)."""
    path = Path(name_or_path)
    if not path.exists() and path.suffix == "":
        return builtin_scene_path(str(name_or_path))
    return path


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene TOML file; every SceneError names the file."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_SCENE_FILE_BYTES + 1)
    except OSError as exc:
        raise SceneError(f"cannot read scene file {path}: {exc.strerror or exc}") from exc
    if len(data) > MAX_SCENE_FILE_BYTES:
        raise SceneError(f"{path}: larger than {MAX_SCENE_FILE_BYTES} bytes: not a scene TOML "
                         "file")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
                         f"{exc.start}): not a scene TOML file") from None
    try:
        return loads_scene(text, name=path.stem)
    except SceneError as exc:
        raise SceneError(f"{path}: {exc}") from None


def loads_scene(text: str, *, name: str = "scene") -> Scene:
    """Parse a scene from TOML text."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"invalid TOML: {exc}") from exc
    return parse_scene(data, name=name, toml_text=text)

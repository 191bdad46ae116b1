"""A small DEM (discrete element method) granular column collapse, in numba.

Monodisperse spheres (diameter d, density rho) in a channel: a floor (z = 0), a back wall
(x = 0), an end wall (x = Lx), two side walls (y = 0, y = W). A column poured against the back
wall behind a gate is released at t = 0 and collapses into a heap under gravity.

Contact model (sphere-sphere and sphere-wall; walls are flat, fixed and of infinite mass):
- normal: linear spring-dashpot, F_n = max(k_n delta - gamma_n v_n, 0) n (no tension), delta
  the overlap (m), v_n the normal approach speed (m/s), gamma_n from the coefficient of
  restitution e: gamma_n = 2 beta sqrt(m_eff k_n), beta = -ln e / sqrt(pi^2 + ln^2 e);
  m_eff = m / 2 between spheres, m against a wall;
- tangential: Cundall-Strack spring with history, F_t = -k_t xi - gamma_t v_t, capped by
  Coulomb friction |F_t| <= mu F_n (xi reset to the sliding force when capped); xi (m) is the
  tangential spring's stretch, projected onto the contact plane every step; k_t = 2/7 k_n;
- rotation: each sphere spins (moment of inertia m d^2 / 10); the tangential force acts at
  the contact point, torque -r n x F_t, and the sliding velocity includes the spin (a pack
  of spheres that cannot roll, tried first, held the column upright at friction 0.5);
- rolling resistance (constant directional torque): -mu_r r* F_n w_rel / |w_rel| against the
  relative spin, r* = r / 2 between spheres and r against a wall, capped so that it stops a
  spin within one step rather than reversing it. It stands in for the angularity of real
  grains; without it round spheres roll on over the floor to the channel's end.

Stiffness: k_n is chosen so that the bottom sphere of the column, carrying the weight of the
n_z spheres above it, is compressed by `max_overlap` diameters: k_n = n_z m g / (eps d).
Time step: explicit symplectic Euler, stable when dt is a small fraction of the contact's
natural period t_c = pi sqrt(m_eff / k_n) (the shortest: sphere-sphere, m_eff = m / 2; the
dashpot only lengthens it); the scene's `dt_fraction` (default 1/20) resolves each collision
with at least 20 steps, rounded down to a whole number of steps per output frame.

Neighbour search: linked cells of edge >= d over the channel (a counting sort each step), so
each sphere tests the 27 cells around its own. Each sphere sums the forces on itself from
all its contacts (in parallel, no atomics); both sides of a contact compute exactly negated
forces (r_ji = -r_ij in floating point), so momentum is conserved to rounding.

Units: SI throughout (m, s, kg, N). Arrays: positions x, velocities v [n, 3] float64.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numba as nb
import numpy as np

# contacts whose tangential history a sphere keeps: equal spheres touch at most 12 others and
# 3 walls (a corner); beyond it a contact would restart its spring every step
MAX_CONTACTS = 16
WALLS = 5  # x = 0, x = Lx, y = 0, y = W, z = 0


POUR_SPACING = 1.25  # pour lattice spacing along x and z, in diameters
POUR_SPACING_Y = 1.05  # least spacing across the channel, in diameters


@dataclass(frozen=True)
class Scene:
    """A column collapse. Lengths in m, times in s.

    The column is poured first: spheres on a loose jittered lattice (spacing 1.25 d) fall
    into the box [0, column x] x channel width behind a gate for up to pour_s (until their
    mean speed is below settle_speed_m_s), which gives a random packing of about
    `packing_fraction` and height column z; then the gate is lifted (t = 0) and the column
    collapses for duration_s."""

    name: str = "dem_column"
    diameter_m: float = 0.005
    column_m: tuple[float, float, float] = (0.1, 0.04, 0.1)  # settled column: x, y, z
    channel_m: tuple[float, float, float] = (0.4, 0.04, 0.2)  # box from the origin: Lx, W, H
    density_kg_m3: float = 2500.0
    friction: float = 0.5  # sphere-sphere Coulomb coefficient
    wall_friction: float = 0.5  # floor, back and end wall
    side_wall_friction: float = 0.0  # smooth channel side walls
    rolling_friction: float = 0.1  # rolling resistance coefficient mu_r (torque mu_r r* F_n)
    restitution: float = 0.5  # normal coefficient of restitution, 0 < e <= 1
    max_overlap: float = 0.005  # overlap under the column's weight, in diameters (sets k_n)
    dt_fraction: float = 0.05  # time step as a fraction of the contact period
    packing_fraction: float = 0.58  # of the poured column; sets the number of spheres
    pour_s: float = 0.5  # longest pour before the gate lifts
    settle_speed_m_s: float = 0.02  # the pour ends early once the mean speed is lower
    duration_s: float = 0.5  # of the collapse, after the gate lifts
    output_interval_s: float = 0.01
    seed: int = 0
    gravity_m_s2: tuple[float, float, float] = field(default=(0.0, 0.0, -9.81))

    def __post_init__(self) -> None:
        def bad(what: str) -> ValueError:
            return ValueError(f"scene {self.name!r}: {what}")

        positive = ("diameter_m", "density_kg_m3", "max_overlap", "dt_fraction", "duration_s",
                    "output_interval_s", "packing_fraction", "pour_s", "settle_speed_m_s")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise bad(f"{name} must be a positive number, got {value!r}")
        for name in ("friction", "wall_friction", "side_wall_friction", "rolling_friction"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise bad(f"{name} must be a number >= 0, got {value!r}")
        if not 0 < self.restitution <= 1:
            raise bad(f"restitution must be in (0, 1], got {self.restitution!r}")
        if self.dt_fraction > 0.2:
            raise bad(f"dt_fraction {self.dt_fraction} is above 0.2 of the contact period: "
                      "the explicit step would not resolve a collision")
        if self.packing_fraction >= 0.74:
            raise bad(f"packing_fraction must be below 0.74 (close packing), got "
                      f"{self.packing_fraction}")
        for name in ("column_m", "channel_m", "gravity_m_s2"):
            if len(getattr(self, name)) != 3:
                raise bad(f"{name} must have 3 components (x, y, z)")
        if any(c > h for c, h in zip(self.column_m, self.channel_m, strict=True)):
            raise bad(f"the column {list(self.column_m)} m does not fit in the channel "
                      f"{list(self.channel_m)} m")
        nx, ny, _ = self.lattice()
        if min(nx, ny) < 1:
            raise bad(f"the column {list(self.column_m)} m holds no sphere of diameter "
                      f"{self.diameter_m:.4g} m along x or y")

    def lattice(self) -> tuple[int, int, int]:
        """Spheres along x, y, z of the pour lattice: as many layers as the column's volume
        at packing_fraction needs."""
        d, (lx, w, h) = self.diameter_m, self.column_m
        nx = int(lx / (POUR_SPACING * d) + 1e-9)
        ny = int(w / (POUR_SPACING_Y * d) + 1e-9)
        spheres = self.packing_fraction * lx * w * h / (math.pi / 6.0 * d ** 3)
        return nx, ny, max(1, math.ceil(spheres / max(nx * ny, 1)))

    @property
    def n(self) -> int:
        return math.prod(self.lattice())

    @property
    def mass_kg(self) -> float:
        return self.density_kg_m3 * math.pi / 6.0 * self.diameter_m ** 3

    @property
    def stiffness_n_m(self) -> float:
        """k_n (N/m): the bottom sphere compressed by max_overlap d under the column."""
        g = float(np.linalg.norm(self.gravity_m_s2)) or 9.81
        layers = self.column_m[2] / self.diameter_m
        return layers * self.mass_kg * g / (self.max_overlap * self.diameter_m)

    @property
    def contact_period_s(self) -> float:
        """The natural period of a sphere-sphere contact, pi sqrt(m_eff / k_n) (s)."""
        return math.pi * math.sqrt(0.5 * self.mass_kg / self.stiffness_n_m)

    @property
    def stable_dt_s(self) -> float:
        """dt_fraction of the contact period (s)."""
        return self.dt_fraction * self.contact_period_s

    @property
    def steps_per_frame(self) -> int:
        return math.ceil(self.output_interval_s / self.stable_dt_s - 1e-9)

    @property
    def dt_s(self) -> float:
        """The time step (s): at most stable_dt_s, a whole number of steps per frame."""
        return self.output_interval_s / self.steps_per_frame

    @property
    def frames(self) -> int:
        """Frames of the collapse, t = 0 included."""
        return int(round(self.duration_s / self.output_interval_s)) + 1

    @property
    def bounds_m(self) -> np.ndarray:
        """The channel [3, 2]: lo, hi per axis (m)."""
        return np.array([[0.0, s] for s in self.channel_m])

    def with_particles(self, n: int) -> Scene:
        """The same column with the diameter that makes about n spheres of it."""
        if n < 8:
            raise ValueError(f"--particles must be at least 8, got {n}")
        d = (self.packing_fraction * math.prod(self.column_m) / (math.pi / 6.0 * n)) ** (1 / 3)
        return replace_scene(self, diameter_m=d)

    def to_toml(self) -> str:
        lines = []
        for key, value in asdict(self).items():
            if isinstance(value, str):
                lines.append(f'{key} = "{value}"')
            elif isinstance(value, tuple | list):
                lines.append(f"{key} = [{', '.join(repr(float(v)) for v in value)}]")
            else:
                lines.append(f"{key} = {value!r}")
        return "\n".join(lines) + "\n"


def replace_scene(scene: Scene, **changes) -> Scene:
    return Scene(**{**asdict(scene), **changes})


def load_scene(path: str | Path) -> Scene:
    """A scene from a TOML file of Scene's fields (top level; lists for the 3-vectors)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the scene: {exc}") from None
    try:
        return load_scene_text(text)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_scene_text(text: str) -> Scene:
    """A scene from TOML text (Scene.to_toml's, or a file's)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"not a scene TOML: {exc}") from None
    known = {f.name for f in fields(Scene)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"unknown scene keys {unknown} (known: {sorted(known)})")
    for key, value in data.items():
        if isinstance(value, list):
            data[key] = tuple(float(v) for v in value)
    return Scene(**data)


def pour_positions(scene: Scene) -> np.ndarray:
    """The pour lattice: spacing 1.25 d along x and z, W / ny across, from the back wall and
    the floor, each sphere offset at random by up to 45 % of its gap to the next, so no two
    touch and the pour packs at random. [n, 3] m."""
    d, (nx, ny, nz) = scene.diameter_m, scene.lattice()
    spacing = np.array([POUR_SPACING * d, scene.column_m[1] / ny, POUR_SPACING * d])
    y0 = 0.5 * (scene.channel_m[1] - scene.column_m[1])
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    x = (np.stack([i.ravel(), j.ravel(), k.ravel()], 1) + 0.5) * spacing
    x[:, 1] += y0
    rng = np.random.default_rng(scene.seed)
    x += rng.uniform(-1.0, 1.0, x.shape) * 0.45 * (spacing - d)
    return x


@nb.njit(cache=True)
def _bin(x, cell_m, dims, start, order):
    """Linked cells as a counting sort: order holds the sphere indices cell by cell, cell c's
    in order[start[c]:start[c + 1]]. Spheres outside the grid go to its border cells."""
    n = x.shape[0]
    cells = np.empty(n, np.int64)
    start[:] = 0
    for i in range(n):
        c = 0
        for a in range(3):
            k = int(x[i, a] / cell_m)
            k = min(max(k, 0), dims[a] - 1)
            c = c * dims[a] + k
        cells[i] = c
        start[c + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[cells[i]]] = i
        fill[cells[i]] += 1


@nb.njit(inline="always")
def _contact(i, partner, delta, nx, ny, nz, vx, vy, vz, kn, gn, kt, gt, mu, dt,
             old_partner, old_count, old_xi, new_partner, new_count, new_xi):
    """Force (N) on sphere i from one contact of overlap delta (m), unit normal n pointing
    towards i, relative velocity v = v_i - v_other (m/s); updates i's tangential history.
    v: the relative velocity of the surfaces at the contact point. Returns the normal force
    fn, the tangential force ft (x, y, z) and the contact's elastic energy (J, seen from i)."""
    vn = vx * nx + vy * ny + vz * nz
    fn = kn * delta - gn * vn
    if fn < 0.0:
        fn = 0.0
    tx, ty, tz = vx - vn * nx, vy - vn * ny, vz - vn * nz  # tangential relative velocity
    xx, xy, xz = 0.0, 0.0, 0.0
    for k in range(old_count[i]):
        if old_partner[i, k] == partner:
            xx, xy, xz = old_xi[i, k, 0], old_xi[i, k, 1], old_xi[i, k, 2]
            break
    xn = xx * nx + xy * ny + xz * nz  # rotate the stretch into the current contact plane
    xx, xy, xz = xx - xn * nx + tx * dt, xy - xn * ny + ty * dt, xz - xn * nz + tz * dt
    ftx, fty, ftz = -kt * xx - gt * tx, -kt * xy - gt * ty, -kt * xz - gt * tz
    ft = math.sqrt(ftx * ftx + fty * fty + ftz * ftz)
    cap = mu * fn
    if ft > cap:  # sliding: Coulomb's limit, the spring set to match it
        s = cap / ft
        ftx, fty, ftz = ftx * s, fty * s, ftz * s
        xx, xy, xz = -(ftx + gt * tx) / kt, -(fty + gt * ty) / kt, -(ftz + gt * tz) / kt
    k = new_count[i]
    if k < new_partner.shape[1]:
        new_partner[i, k] = partner
        new_xi[i, k, 0], new_xi[i, k, 1], new_xi[i, k, 2] = xx, xy, xz
        new_count[i] = k + 1
    energy = 0.5 * kn * delta * delta + 0.5 * kt * (xx * xx + xy * xy + xz * xz)
    return fn, ftx, fty, ftz, energy


@nb.njit(inline="always")
def _rolling(wx, wy, wz, fn, arm, limit, mu_r):
    """Rolling resistance torque against the relative spin w (rad/s): mu_r arm fn (N m,
    arm the effective radius, m), at most `limit` / |w| so it stops the spin within a step
    instead of reversing it."""
    mag = math.sqrt(wx * wx + wy * wy + wz * wz)
    if mag == 0.0:
        return 0.0, 0.0, 0.0
    s = min(mu_r * arm * fn, limit * mag) / mag
    return -s * wx, -s * wy, -s * wz


@nb.njit(parallel=True, cache=True)
def _forces(x, v, w, d, box, params, cell_m, dims, start, order, old_partner, old_count,
            old_xi, new_partner, new_count, new_xi, f, torque, energy):
    """Contact forces f [n, 3] (N), torques [n, 3] (N m) and elastic energy per sphere [n]
    (J; a sphere-sphere contact's energy is split between its two spheres) of spheres at
    x [n, 3] (m) moving at v [n, 3] (m/s), spinning at w [n, 3] (rad/s). params: kn, gn,
    kt, gt (sphere-sphere), gn_w, gt_w (against a wall), mu, mu_wall, mu_side, dt, mu_r,
    inertia (kg m^2)."""
    kn, gn, kt, gt, gn_w, gt_w, mu, mu_wall, mu_side, dt = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6], params[7],
        params[8], params[9])
    mu_r, inertia = params[10], params[11]
    n = x.shape[0]
    r = 0.5 * d
    for i in nb.prange(n):
        new_count[i] = 0
        fx, fy, fz, e = 0.0, 0.0, 0.0, 0.0
        tx, ty, tz = 0.0, 0.0, 0.0
        c0 = min(max(int(x[i, 0] / cell_m), 0), dims[0] - 1)
        c1 = min(max(int(x[i, 1] / cell_m), 0), dims[1] - 1)
        c2 = min(max(int(x[i, 2] / cell_m), 0), dims[2] - 1)
        for cx in range(max(c0 - 1, 0), min(c0 + 2, dims[0])):
            for cy in range(max(c1 - 1, 0), min(c1 + 2, dims[1])):
                for cz in range(max(c2 - 1, 0), min(c2 + 2, dims[2])):
                    c = (cx * dims[1] + cy) * dims[2] + cz
                    for s in range(start[c], start[c + 1]):
                        j = order[s]
                        if j == i:
                            continue
                        rx, ry, rz = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
                        dist2 = rx * rx + ry * ry + rz * rz
                        if dist2 >= d * d or dist2 == 0.0:
                            continue
                        dist = math.sqrt(dist2)
                        nx, ny, nz = rx / dist, ry / dist, rz / dist  # from j towards i
                        # surface velocity at the contact: v_i - v_j - r (w_i + w_j) x n
                        sx, sy, sz = w[i, 0] + w[j, 0], w[i, 1] + w[j, 1], w[i, 2] + w[j, 2]
                        fn, gx, gy, gz, ge = _contact(
                            i, j, d - dist, nx, ny, nz,
                            v[i, 0] - v[j, 0] - r * (sy * nz - sz * ny),
                            v[i, 1] - v[j, 1] - r * (sz * nx - sx * nz),
                            v[i, 2] - v[j, 2] - r * (sx * ny - sy * nx), kn, gn, kt, gt, mu, dt,
                            old_partner, old_count, old_xi, new_partner, new_count, new_xi)
                        fx, fy, fz = fx + fn * nx + gx, fy + fn * ny + gy, fz + fn * nz + gz
                        # torque of the tangential force at the contact point: -r n x ft
                        tx -= r * (ny * gz - nz * gy)
                        ty -= r * (nz * gx - nx * gz)
                        tz -= r * (nx * gy - ny * gx)
                        # rolling resistance: arm r / 2 (equal spheres), relative spin w_i - w_j
                        qx, qy, qz = _rolling(w[i, 0] - w[j, 0], w[i, 1] - w[j, 1],
                                              w[i, 2] - w[j, 2], fn, 0.5 * r,
                                              0.5 * inertia / dt, mu_r)
                        tx, ty, tz = tx + qx, ty + qy, tz + qz
                        e += 0.5 * ge
        # walls: partner -1 - w; normal into the channel
        for k in range(WALLS):
            a = k // 2 if k < 4 else 2
            side = 1.0 if k % 2 == 0 else -1.0
            wall = box[a, 0] if side > 0 else box[a, 1]
            delta = r - side * (x[i, a] - wall)
            if delta <= 0.0:
                continue
            nx, ny, nz = (side if a == 0 else 0.0), (side if a == 1 else 0.0), (side if a == 2 else 0.0)
            m_wall = mu_side if a == 1 else mu_wall
            fn, gx, gy, gz, ge = _contact(
                i, -1 - k, delta, nx, ny, nz, v[i, 0] - r * (w[i, 1] * nz - w[i, 2] * ny),
                v[i, 1] - r * (w[i, 2] * nx - w[i, 0] * nz),
                v[i, 2] - r * (w[i, 0] * ny - w[i, 1] * nx), kn, gn_w, kt, gt_w, m_wall, dt,
                old_partner, old_count, old_xi, new_partner, new_count, new_xi)
            fx, fy, fz = fx + fn * nx + gx, fy + fn * ny + gy, fz + fn * nz + gz
            tx -= r * (ny * gz - nz * gy)
            ty -= r * (nz * gx - nx * gz)
            tz -= r * (nx * gy - ny * gx)
            qx, qy, qz = _rolling(w[i, 0], w[i, 1], w[i, 2], fn, r, inertia / dt, mu_r)
            tx, ty, tz = tx + qx, ty + qy, tz + qz
            e += ge
        f[i, 0], f[i, 1], f[i, 2] = fx, fy, fz
        torque[i, 0], torque[i, 1], torque[i, 2] = tx, ty, tz
        energy[i] = e


@nb.njit(cache=True)
def _integrate(x, v, w, f, torque, inv_m, inv_i, g, dt):
    """Symplectic Euler: v += dt (f / m + g), then x += dt v; w += dt torque / I."""
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] += dt * (f[i, a] * inv_m + g[a])
            x[i, a] += dt * v[i, a]
            w[i, a] += dt * torque[i, a] * inv_i


class Simulation:
    """A column collapse of `scene`: x, v [n, 3] (m, m/s), x0 the positions when the gate
    lifts, step count and time (s) from then. `pour()` fills the column behind the gate and
    lifts it; `advance()` takes one time step. Given positions [n, 3] (m) and velocities
    [n, 3] (m/s), it starts from those instead, in the open channel (no gate, no pour)."""

    def __init__(self, scene: Scene, positions: np.ndarray | None = None,
                 velocities: np.ndarray | None = None) -> None:
        self.scene = s = scene
        given = positions is not None
        self.x = np.array(positions, np.float64) if given else pour_positions(s)
        if self.x.ndim != 2 or self.x.shape[1] != 3:
            raise ValueError(f"positions must be [n, 3] (m), got shape {self.x.shape}")
        self.x0 = self.x.copy()
        self.v = (np.array(velocities, np.float64) if velocities is not None
                  else np.zeros_like(self.x))
        if self.v.shape != self.x.shape:
            raise ValueError(f"velocities must be [n, 3] like positions {self.x.shape}, got "
                             f"{self.v.shape}")
        self.w = np.zeros_like(self.x)  # angular velocity [n, 3] (rad/s)
        self.n = n = len(self.x)
        self.ids = np.arange(n, dtype=np.int64)
        self.step, self.time_s, self.dt_s = 0, 0.0, s.dt_s
        self.pour_steps, self.pour_s = 0, 0.0
        self.mass_kg = s.mass_kg
        self.inertia_kg_m2 = 0.1 * s.mass_kg * s.diameter_m ** 2  # solid sphere: 2/5 m r^2
        self.gravity = np.asarray(s.gravity_m_s2, dtype=np.float64)
        self.box = s.bounds_m
        if not given:
            self.box[0, 1] = s.column_m[0]  # the gate: the end wall, at the column's front
        kn = s.stiffness_n_m
        kt = 2.0 / 7.0 * kn
        ln_e = math.log(s.restitution)
        beta = -ln_e / math.sqrt(math.pi ** 2 + ln_e ** 2)
        m_pair, m_wall = 0.5 * s.mass_kg, s.mass_kg

        def damping(k, m):
            return 2.0 * beta * math.sqrt(m * k)

        self.params = np.array([kn, damping(kn, m_pair), kt, damping(kt, m_pair),
                                damping(kn, m_wall), damping(kt, m_wall), s.friction,
                                s.wall_friction, s.side_wall_friction, self.dt_s,
                                s.rolling_friction, self.inertia_kg_m2])
        self.cell_m = s.diameter_m
        # the cells cover the channel and the pour above it (spheres above go to the top cells)
        top = max(s.channel_m[2], float(self.x[:, 2].max()) + s.diameter_m)
        extent = (s.channel_m[0], s.channel_m[1], top)
        self.dims = np.array([max(1, int(c / self.cell_m)) for c in extent], np.int64)
        self.start = np.zeros(int(np.prod(self.dims)) + 1, np.int64)
        self.order = np.empty(n, np.int64)
        self.hist = [(np.full((n, MAX_CONTACTS), 0, np.int64), np.zeros(n, np.int64),
                      np.zeros((n, MAX_CONTACTS, 3))) for _ in range(2)]
        self.f = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
        self.contact_energy = np.zeros(n)

    def pour(self) -> None:
        """Let the spheres fall, frictionless, behind the gate until their mean speed is
        below settle_speed_m_s (after at least a free fall from the top) or pour_s has passed;
        then lift the gate (the end wall moves to the channel's end) and start the clock."""
        s = self.scene
        friction = self.params[[6, 7, 8, 10]]
        self.params[[6, 7, 8, 10]] = 0.0  # a frictionless pour packs densely and settles fast
        fall_s = math.sqrt(2.0 * float(self.x[:, 2].max()) / max(-self.gravity[2], 1e-9))
        check = max(1, int(0.005 / self.dt_s))  # look at the speeds every 5 ms
        while self.time_s < s.pour_s:
            self.advance()
            if self.step % check == 0 and self.time_s > fall_s:
                if float(np.linalg.norm(self.v, axis=1).mean()) < s.settle_speed_m_s:
                    break
        self.pour_steps, self.pour_s = self.step, self.time_s
        self.box[0, 1] = s.channel_m[0]
        self.params[[6, 7, 8, 10]] = friction
        self.x0 = self.x.copy()
        self.v[:] = 0.0  # the column starts at rest (its last few mm/s of settling dropped)
        self.w[:] = 0.0
        self.step, self.time_s = 0, 0.0

    def advance(self) -> None:
        """One explicit time step of dt_s."""
        (op, oc, ox), (np_, nc, nx) = self.hist
        _bin(self.x, self.cell_m, self.dims, self.start, self.order)
        _forces(self.x, self.v, self.w, self.scene.diameter_m, self.box, self.params,
                self.cell_m, self.dims, self.start, self.order, op, oc, ox, np_, nc, nx, self.f,
                self.torque, self.contact_energy)
        _integrate(self.x, self.v, self.w, self.f, self.torque, 1.0 / self.mass_kg,
                   1.0 / self.inertia_kg_m2, self.gravity, self.dt_s)
        self.hist.reverse()
        self.step += 1
        self.time_s = self.step * self.dt_s

    # diagnostics: energies (J) and momentum (kg m/s)
    def kinetic_energy_j(self) -> float:
        """Translational and rotational kinetic energy."""
        return 0.5 * (self.mass_kg * float(np.einsum("ij,ij->", self.v, self.v))
                      + self.inertia_kg_m2 * float(np.einsum("ij,ij->", self.w, self.w)))

    def energy_j(self) -> float:
        """Total mechanical energy: kinetic, gravity's and the contact springs'."""
        return self.kinetic_energy_j() + self.potential_energy_j() + self.elastic_energy_j()

    def potential_energy_j(self) -> float:
        """Gravity's potential energy, relative to the sphere centres at the origin."""
        return -self.mass_kg * float((self.x @ self.gravity).sum())

    def elastic_energy_j(self) -> float:
        """Energy stored in the contact springs at the last computed step."""
        return float(self.contact_energy.sum())

    def momentum(self) -> np.ndarray:
        return self.mass_kg * self.v.sum(axis=0)

    def contacts_per_sphere(self) -> float:
        return float(self.hist[0][1].mean())


def runout_m(x: np.ndarray, q: float = 99.0) -> float:
    """The front of the heap: the q-th percentile of x (m) of positions [n, 3]."""
    return float(np.percentile(x[:, 0], q))


def height_m(x: np.ndarray, q: float = 99.0) -> float:
    """The top of the heap: the q-th percentile of z (m) of positions [n, 3]."""
    return float(np.percentile(x[:, 2], q))

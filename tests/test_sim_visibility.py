"""Occlusion culling (insitu.visibility): the particles dropped never show.

Each case renders a dense, jittered block of spheres with every particle and with only the
kept ones, through the server's own ray caster, and requires identical pixels."""

import numpy as np
import pytest

from minority.insitu.payload import Particles, cull
from minority.insitu.visibility import visible_mask
from minority.protocol.errors import SpecError
from minority.protocol.spec import Camera, Region, Spec, View, Window, inside_mask
from minority.render_server.render import prepare, render

SPACING = 0.01  # m
RADIUS = 0.5 * SPACING


def block(shape=(24, 12, 16), jitter=0.25, seed=3) -> np.ndarray:
    """[n, 3] m: a lattice block with its corner at the origin, each particle jittered."""
    rng = np.random.default_rng(seed)
    idx = np.stack(np.meshgrid(*(np.arange(s) for s in shape), indexing="ij"), -1).reshape(-1, 3)
    return (idx + 0.5 + rng.uniform(-jitter, jitter, idx.shape)) * SPACING


def image(positions, values, view):
    return render(prepare(positions, RADIUS), values, view).copy()


CAMERAS = {
    "side": Camera((0.12, -0.45, 0.08), (0.12, 0.06, 0.08), (0, 0, 1), 30.0),
    "aerial": Camera((0.40, -0.30, 0.35), (0.12, 0.06, 0.06), (0, 0, 1), 30.0),
    "close": Camera((0.05, -0.12, 0.10), (0.12, 0.06, 0.06), (0, 0, 1), 40.0),  # cuts the block
    "top_parallel": Camera((0.12, 0.06, 0.6), (0.12, 0.06, 0.0), (0, 1, 0), 30.0,
                           parallel_projection=True, parallel_scale_m=0.1),
}


@pytest.mark.parametrize("name", list(CAMERAS))
def test_dropped_particles_never_show(name):
    pos = block()
    values = np.random.default_rng(0).random(len(pos))  # a color per particle
    view = View(name, CAMERAS[name], 160, 120, range=(0.0, 1.0))
    keep = visible_mask(pos, view, RADIUS)
    assert 0.05 < keep.mean() < 0.6, keep.mean()  # it culls, and keeps the surface
    np.testing.assert_array_equal(image(pos[keep], values[keep], view), image(pos, values, view))


def test_the_faces_are_kept_and_the_interior_dropped():
    pos = block(shape=(10, 10, 10), jitter=0.2)
    ijk = np.rint(pos / SPACING - 0.5).astype(int)
    # sees the faces y = 0, x = 9 and z = 9 of the cube, obliquely
    view = View("f", Camera((0.3, -1.0, 0.4), (0.05, 0.05, 0.05), (0, 0, 1), 10.0), 200, 200)
    keep = visible_mask(pos, view, RADIUS)
    assert keep[ijk[:, 1] == 0].all()
    deep = (ijk[:, 1] >= 3) & (ijk[:, 0] <= 6) & (ijk[:, 2] <= 6)  # 3 layers behind each face
    assert keep[deep].mean() < 0.05
    values = np.random.default_rng(1).random(len(pos))
    np.testing.assert_array_equal(image(pos[keep], values[keep], view), image(pos, values, view))


def test_out_of_view_and_behind_the_camera_are_dropped():
    view = View("v", Camera((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0, 0, 1), 30.0), 64, 64)
    pts = np.array([[0.0, 0.2, 0.0],  # straight ahead, a disk of 3 px
                    [5.0, 1.0, 0.0],  # far off to the right
                    [0.0, -1.0, 0.0],  # behind
                    [0.0, 0.002, 0.0]])  # the sphere holds the camera: kept, the caster decides
    assert visible_mask(pts, view, RADIUS).tolist() == [True, False, False, True]


def test_spec_occlusion_cull_round_trip_validation_and_request():
    cam = CAMERAS["side"]
    culled = View("a", cam, occlusion_cull=True, schedule=(Window(every_steps=1),))
    plain = View("b", cam, schedule=(Window(every_steps=2),))
    spec = Spec("run", (culled, plain))
    assert Spec.from_dict(spec.to_dict()) == spec
    assert "occlusion_cull" not in spec.to_dict()["views"][1]  # old specs encode as before
    assert spec.request(1, 0.1).visible_in == ((culled, None),)
    assert spec.request(2, 0.2).visible_in == ()  # view b needs every particle
    bad = spec.to_dict()
    bad["views"][0]["occlusion_cull"] = "yes"
    with pytest.raises(SpecError, match=r"views\[0\]\.occlusion_cull"):
        Spec.from_dict(bad)


def _particles(pos):
    n = len(pos)
    return Particles(pos.copy(), np.arange(n), {"velocity": np.zeros((n, 3)),
                                                 "displacement": np.full((n, 3), -0.001)})


@pytest.mark.parametrize("decimate", [1, 2])
def test_each_view_is_culled_among_what_it_draws(decimate):
    """View a shows only the back half of the block (its region) and, with decimate 2, only
    even ids: the front half and odd ids, which view b draws, must not hide a's particles."""
    pos = block(shape=(12, 12, 8))
    values = np.random.default_rng(2).random(len(pos))
    back = Region("back", (0.0, 0.06, 0.0), (1.0, 1.0, 1.0))
    everything = Region("all", (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    a = View("a", CAMERAS["side"], 160, 120, decimate=decimate, occlusion_cull=True,
             schedule=(Window(regions=("back",)),))
    b = View("b", CAMERAS["top_parallel"], 160, 120, occlusion_cull=True,
             schedule=(Window(regions=("all",)),))
    spec = Spec("run", (a, b), regions=(back, everything))
    sent = cull(_particles(pos), spec.request(20, 0.0), RADIUS)
    assert len(sent["positions"]) < len(pos)
    # what the server draws in view a, from what was sent and from everything
    ids = np.flatnonzero(inside_mask(pos, (back,)) & (np.arange(len(pos)) % decimate == 0))
    got = sent["positions"].astype(np.float64)
    drawn = inside_mask(got, (back,))
    index = {tuple(p): i for i, p in enumerate(pos.astype(np.float32).tolist())}
    rows = np.array([index[tuple(p)] for p in got[drawn].astype(np.float32).tolist()], int)
    rows = rows[rows % decimate == 0]
    np.testing.assert_array_equal(image(pos[rows], values[rows], a), image(pos[ids], values[ids], a))


def test_cull_sends_the_union_of_what_the_views_see():
    pos = block(shape=(12, 8, 8))
    n = len(pos)
    ps = _particles(pos)
    side = View("side", CAMERAS["side"], 160, 120, occlusion_cull=True)
    top = View("top", CAMERAS["top_parallel"], 160, 120, occlusion_cull=True)
    spec = Spec("run", (side, top))
    request = spec.request(20, 0.0)
    sent = cull(ps, request, RADIUS)
    want = visible_mask(pos, side, RADIUS) | visible_mask(pos, top, RADIUS)
    np.testing.assert_array_equal(sent["positions"], pos[want].astype(np.float32))
    assert sent["displacement"].shape == (want.sum(), 3) and want.sum() < n
    assert len(cull(ps, request)["positions"]) == n  # no radius given: nothing culled


@pytest.mark.parametrize("name", ["side", "aerial", "top_parallel"])
def test_a_random_heap_renders_the_same(name):
    """Not a lattice: a wedge-shaped deposit, uniformly random, at the lattice's density."""
    rng = np.random.default_rng(7)
    n = 6000
    pts = rng.random((3 * n, 3)) * [0.24, 0.12, 0.12]
    pts = pts[pts[:, 2] < 0.12 * (1.0 - pts[:, 0] / 0.24)][:n]  # under the slope
    values = rng.random(len(pts))
    view = View(name, CAMERAS[name], 320, 240)
    keep = visible_mask(pts, view, RADIUS)
    assert keep.mean() < 0.6
    np.testing.assert_array_equal(image(pts[keep], values[keep], view), image(pts, values, view))

"""The ray tracer against brute force (every ray against every sphere): the same hit
particle per pixel, also for spheres straddling brick faces."""

import numpy as np
import pytest

from minority.protocol.spec import Camera
from minority.render_server.accel import build_grids
from minority.render_server.bricks import repartition
from minority.render_server.camera import primary_rays, ray_frame
from minority.render_server.cast import cast
from minority.render_server.trace import trace, trace_brute_force

WIDTH, HEIGHT = 64, 48


def scene(kind: str, rng):
    if kind == "uniform":
        return rng.random((1500, 3)), 0.02
    if kind == "column":  # a collapsed-column-like heap, dense near the floor
        x = rng.random(1500) * 1.0
        z = rng.random(1500) * 0.3 * (1.0 - x) ** 2
        return np.c_[x, rng.random(1500) * 0.2, z], 0.012
    if kind == "straddle":  # spheres sitting on the median planes of a 2x2x2 split
        pts = rng.random((400, 3))
        pts[:200, 0] = 0.5 + rng.normal(scale=0.01, size=200)
        pts[200:, 1] = 0.5 + rng.normal(scale=0.01, size=200)
        return pts, 0.04
    raise ValueError(kind)


CAMERAS = [Camera((0.5, -1.5, 0.6), (0.5, 0.5, 0.3), (0, 0, 1), 40.0),
           Camera((2.0, 1.8, 1.5), (0.4, 0.3, 0.2), (0, 0, 1), 30.0),
           Camera((0.5, 0.5, 3.0), (0.5, 0.5, 0.0), (0, 1, 0), 30.0, True, 0.6)]


@pytest.mark.parametrize("kind", ["uniform", "column", "straddle"])
@pytest.mark.parametrize("n_bricks", [1, 2, 8])
def test_same_hit_as_brute_force(kind, n_bricks):
    rng = np.random.default_rng(len(kind) + n_bricks)
    positions, radius = scene(kind, rng)
    positions = positions.astype(np.float32)
    bricks = repartition(positions, radius, n_bricks)
    grids = build_grids(positions, radius, bricks)
    hits = 0
    for cam in CAMERAS:
        origins, dirs = primary_rays(cam, WIDTH, HEIGHT)
        t, ids = trace(origins, dirs, positions, radius, bricks, grids)
        t_ref, ids_ref = trace_brute_force(origins, dirs, positions, radius)
        np.testing.assert_array_equal(ids, ids_ref)
        # same formula, other operand order: distances agree to rounding
        np.testing.assert_allclose(t[ids >= 0], t_ref[ids_ref >= 0], rtol=1e-9)
        hits += (ids >= 0).sum()
    assert hits > 0.05 * len(CAMERAS) * WIDTH * HEIGHT  # the scene is in view, not a blank test


def test_bricks_are_balanced_and_disjoint():
    rng = np.random.default_rng(1)
    positions = rng.random((10_000, 3)).astype(np.float32)
    bricks = repartition(positions, 0.005, 8)
    assert bricks.owned.tolist() == [1250] * 8
    starts = bricks.start[:-1]
    owned = np.concatenate([bricks.members[s:s + o] for s, o in zip(starts, bricks.owned, strict=True)])
    assert sorted(owned.tolist()) == list(range(10_000))
    for b in range(8):  # owned centers lie in their (disjoint) box
        pts = positions[bricks.members[bricks.start[b]:bricks.start[b] + bricks.owned[b]]]
        assert (pts >= bricks.boxes[b, 0] - 1e-7).all() and (pts <= bricks.boxes[b, 1] + 1e-7).all()
    for a in range(8):
        for b in range(a + 1, 8):
            overlap = np.minimum(bricks.boxes[a, 1], bricks.boxes[b, 1]) - \
                np.maximum(bricks.boxes[a, 0], bricks.boxes[b, 0])
            assert (overlap <= 1e-12).any()


@pytest.mark.parametrize("case", ["one", "same_point"])
def test_degenerate_scenes(case):
    positions = np.zeros((1 if case == "one" else 50, 3), np.float32) + 0.5
    bricks = repartition(positions, 0.1, 4)
    grids = build_grids(positions, 0.1, bricks)
    origins, dirs = primary_rays(CAMERAS[0], WIDTH, HEIGHT)
    t, ids = trace(origins, dirs, positions, 0.1, bricks, grids)
    t_ref, ids_ref = trace_brute_force(origins, dirs, positions, 0.1)
    np.testing.assert_array_equal(ids, ids_ref)
    assert (ids >= 0).sum() > 0


@pytest.mark.parametrize("kind", ["uniform", "column", "straddle"])
def test_object_order_cast_equals_brute_force(kind):
    rng = np.random.default_rng(len(kind))
    positions, radius = scene(kind, rng)
    positions = positions.astype(np.float32)
    near = Camera((0.5, 0.5, 0.5), (0.5, 1.5, 0.5), (0, 0, 1), 60.0)  # inside the cloud
    for cam in CAMERAS + [near]:
        origins, dirs = primary_rays(cam, WIDTH, HEIGHT)
        t, ids = cast(positions, radius, ray_frame(cam, WIDTH, HEIGHT), WIDTH, HEIGHT)
        t_ref, ids_ref = trace_brute_force(origins, dirs, positions, radius)
        np.testing.assert_array_equal(ids, ids_ref)
        np.testing.assert_allclose(t[ids >= 0], t_ref[ids_ref >= 0], rtol=1e-9)


@pytest.mark.parametrize("seed", range(10))
def test_object_order_cast_random_cameras(seed):
    rng = np.random.default_rng(100 + seed)
    positions = rng.normal(scale=0.3, size=(400, 3)).astype(np.float32)
    radius = float(rng.uniform(0.005, 0.08))
    for _ in range(3):
        cam = Camera(tuple(rng.uniform(-2, 2, 3)), tuple(rng.normal(scale=0.2, size=3)),
                     tuple(rng.normal(size=3)), float(rng.uniform(15, 90)),
                     bool(rng.random() < 0.3), float(rng.uniform(0.3, 1.5)))
        origins, dirs = primary_rays(cam, WIDTH, HEIGHT)
        _, ids = cast(positions, radius, ray_frame(cam, WIDTH, HEIGHT), WIDTH, HEIGHT)
        _, ids_ref = trace_brute_force(origins, dirs, positions, radius)
        np.testing.assert_array_equal(ids, ids_ref)


@pytest.mark.parametrize("kind", ["uniform", "column"])
def test_casting_the_bands_in_small_groups_changes_no_hit(kind, monkeypatch):
    """A record budget of a few rows' worth casts the image in many band groups (at 8M
    particles the default budget does the same): every hit as with one group."""
    import minority.render_server.cast as cast_module

    rng = np.random.default_rng(len(kind) + 7)
    positions, radius = scene(kind, rng)
    positions = positions.astype(np.float32)
    keys = rng.permutation(len(positions)).astype(np.int64)
    for cam in CAMERAS:
        frame = ray_frame(cam, WIDTH, HEIGHT)
        t1, ids1 = cast(positions, radius, frame, WIDTH, HEIGHT, keys=keys)
        monkeypatch.setattr(cast_module, "RECORD_BYTES", 4096)
        t2, ids2 = cast(positions, radius, frame, WIDTH, HEIGHT, keys=keys)
        monkeypatch.undo()
        assert (ids1 >= 0).any()
        np.testing.assert_array_equal(ids2, ids1)
        np.testing.assert_array_equal(t2, t1)

"""protocol.projection, the one camera model: the renderer's rays are its inverse, the
former matrix form (VTK's composite projection) equals it to rounding, and the renderer and
the sim's visibility agree on which particles are in frame, at the frame edges too."""

import math

import numpy as np
import pytest

from minority.insitu.visibility import visible_mask
from minority.protocol.projection import (
    camera_basis,
    camera_coordinates,
    in_view,
    pixels_per_unit,
    project,
)
from minority.protocol.spec import Camera, View
from minority.render_server.camera import primary_rays, ray_frame
from minority.render_server.cast import cast
from minority.render_server.render import prepare, render

WIDTH, HEIGHT = 64, 48  # px
ROUND_TRIP_PX = 1e-9  # px: a projection and its inverse, in float64
CAMERAS = {
    "perspective": Camera((0.3, -1.5, 0.4), (0.3, 0.0, 0.2), (0, 0, 1), 30.0),
    "parallel": Camera((0.3, -1.5, 0.4), (0.3, 0.0, 0.2), (0, 0, 1), 30.0,
                       parallel_projection=True, parallel_scale_m=0.25),
}


def matrix_pixels(cam: Camera, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """The renderer's former projection: OpenGL/VTK view and projection matrices."""
    b = camera_basis(cam)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = b.right, b.up, -b.forward
    view[:3, 3] = -view[:3, :3] @ b.position
    near, far, aspect = 0.01, 1000.0, width / height
    proj = np.zeros((4, 4))
    if cam.parallel_projection:
        s = cam.parallel_scale_m
        proj[0, 0], proj[1, 1], proj[3, 3] = 1.0 / (s * aspect), 1.0 / s, 1.0
        proj[2, 2], proj[2, 3] = -2.0 / (far - near), -(far + near) / (far - near)
    else:
        f = 1.0 / math.tan(math.radians(cam.view_angle_deg) / 2.0)
        proj[0, 0], proj[1, 1], proj[3, 2] = f / aspect, f, -1.0
        proj[2, 2], proj[2, 3] = -(far + near) / (far - near), -2.0 * far * near / (far - near)
    h = np.c_[points, np.ones(len(points))] @ (proj @ view).T
    ndc = h[:, :2] / h[:, 3:4]
    return np.c_[(ndc[:, 0] + 1.0) * 0.5 * width, (1.0 - ndc[:, 1]) * 0.5 * height]


def world_points(cam: Camera, x, y, depth) -> np.ndarray:
    """[n, 3] m: the points at pixel coordinates x, y [n] (px) and camera depth [n] (m),
    built from the renderer's ray frame (its rays' own arithmetic, not the projection's)."""
    f = ray_frame(cam, WIDTH, HEIGHT)
    gx = 2.0 * np.asarray(x, float) / WIDTH - 1.0
    gy = 1.0 - 2.0 * np.asarray(y, float) / HEIGHT
    scale = np.asarray(depth, float) if f.perspective else np.ones(len(gx))
    sx, sy = gx * f.half_width * scale, gy * f.half_height * scale
    return (f.position + np.asarray(depth, float)[:, None] * f.forward
            + sx[:, None] * f.right + sy[:, None] * f.up)


@pytest.mark.parametrize("seed", range(5))
def test_projection_equals_the_matrix_form(seed):
    rng = np.random.default_rng(seed)
    for _ in range(10):
        cam = Camera(tuple(rng.uniform(-3, 3, 3)), tuple(rng.uniform(-0.5, 0.5, 3)),
                     tuple(rng.normal(size=3)), rng.uniform(10, 80), bool(rng.random() < 0.5),
                     rng.uniform(0.2, 2.0))
        b = camera_basis(cam)
        pts = np.asarray(cam.focal_point) + rng.normal(scale=0.3, size=(300, 3))
        pts = pts[(pts - b.position) @ b.forward > 0.05]
        ours = project(pts, cam, WIDTH, HEIGHT)
        np.testing.assert_allclose(ours, matrix_pixels(cam, pts, WIDTH, HEIGHT),
                                   rtol=0.0, atol=ROUND_TRIP_PX)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_rays_project_to_their_pixel_centers(name):
    cam = CAMERAS[name]
    origins, dirs = primary_rays(cam, WIDTH, HEIGHT)
    q = np.arange(WIDTH * HEIGHT)
    t = np.random.default_rng(1).uniform(0.5, 3.0, len(q))  # m along the unit ray
    px = project(origins + t[:, None] * dirs, cam, WIDTH, HEIGHT)
    centers = np.c_[q % WIDTH + 0.5, q // WIDTH + 0.5]
    np.testing.assert_allclose(px, centers, rtol=0.0, atol=ROUND_TRIP_PX)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_points_on_the_frame_edges(name):
    """Points a hair inside and outside the four edges and the corners: the renderer's
    projection lands them there, and the frustum test keeps exactly the inside ones."""
    cam = CAMERAS[name]
    eps = 1e-6  # px, far above rounding
    a = np.linspace(0.0, 1.0, 9)[1:-1]
    zero, one = np.zeros_like(a), np.ones_like(a)
    # points on the edges and corners [m, 2] (px) and their outward normals [m, 2]
    edge = np.r_[np.c_[zero, a * HEIGHT], np.c_[one * WIDTH, a * HEIGHT],
                 np.c_[a * WIDTH, zero], np.c_[a * WIDTH, one * HEIGHT],
                 [[0.0, 0.0], [WIDTH, 0.0], [0.0, HEIGHT], [WIDTH, HEIGHT]]]
    normal = np.r_[np.c_[-one, zero], np.c_[one, zero], np.c_[zero, -one], np.c_[zero, one],
                   [[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]]]
    xy = np.r_[edge - eps * normal, edge + eps * normal]
    inside = np.r_[np.ones(len(edge), bool), np.zeros(len(edge), bool)]
    depth = np.linspace(0.8, 2.5, len(xy))  # m
    pts = world_points(cam, xy[:, 0], xy[:, 1], depth)
    px = project(pts, cam, WIDTH, HEIGHT)
    np.testing.assert_allclose(px, xy, rtol=0.0, atol=ROUND_TRIP_PX)
    renderer_in = ((px[:, 0] >= 0) & (px[:, 0] <= WIDTH) & (px[:, 1] >= 0)
                   & (px[:, 1] <= HEIGHT))
    np.testing.assert_array_equal(renderer_in, inside)
    np.testing.assert_array_equal(in_view(pts, cam, WIDTH, HEIGHT), inside)
    # behind the camera: never in view, whatever its pixel coordinates
    assert not in_view(world_points(cam, xy[:, 0], xy[:, 1], -depth), cam, WIDTH, HEIGHT).any()


def edge_spheres(cam: Camera):
    """Spheres of about 2.5 px radius: centers on the four edge lines and corners (half of
    each in frame, shown), the same pushed out by 2.5 radii (wholly out of frame), and a
    few inside; spaced 10 px apart so none hides another. Returns positions [n, 3] (m),
    radius (m), and the masks on_edge, outside [n]."""
    centers_x = np.arange(12.5, WIDTH - 9.0, 10.0)
    centers_y = np.arange(12.5, HEIGHT - 9.0, 10.0)
    rows = []  # (x, y, outward x, outward y)
    for y in centers_y:
        rows += [(0.0, y, -1.0, 0.0), (WIDTH, y, 1.0, 0.0)]
    for x in centers_x:
        rows += [(x, 0.0, 0.0, -1.0), (x, HEIGHT, 0.0, 1.0)]
    rows += [(0.0, 0.0, -1.0, -1.0), (WIDTH, 0.0, 1.0, -1.0), (0.0, HEIGHT, -1.0, 1.0),
             (WIDTH, HEIGHT, 1.0, 1.0)]
    e = np.array(rows)
    r_px = 2.5
    inner = np.array([[x, y] for x in (22.5, 42.5) for y in (22.5,)])
    xy = np.r_[e[:, :2], e[:, :2] + 2.5 * r_px * e[:, 2:], inner]
    n_edge = len(e)
    depth = 1.6 * (1.0 + 0.15 * np.sin(np.arange(len(xy))))  # m, varied
    radius = r_px * 1.6 / pixels_per_unit(cam, HEIGHT)  # m: r_px at depth 1.6 m
    if cam.parallel_projection:
        radius = r_px / pixels_per_unit(cam, HEIGHT)
    on_edge = np.arange(len(xy)) < n_edge
    outside = (np.arange(len(xy)) >= n_edge) & (np.arange(len(xy)) < 2 * n_edge)
    return world_points(cam, xy[:, 0], xy[:, 1], depth), radius, on_edge, outside


@pytest.mark.parametrize("name", list(CAMERAS))
def test_renderer_and_visibility_agree_at_the_frame_edges(name):
    cam = CAMERAS[name]
    pos, radius, on_edge, outside = edge_spheres(cam)
    view = View(name, cam, WIDTH, HEIGHT, range=(0.0, 1.0))
    _, ids = cast(pos, radius, ray_frame(cam, WIDTH, HEIGHT), WIDTH, HEIGHT)
    shown = np.zeros(len(pos), bool)
    shown[ids[ids >= 0]] = True
    keep = visible_mask(pos, view, radius)
    assert shown[on_edge].all() and keep[on_edge].all()  # half in frame: drawn and sent
    assert not shown[outside].any() and not keep[outside].any()  # out of frame: neither
    assert keep[shown].all()  # the sim never leaves out what the renderer draws
    # what the sim keeps reaches the frame by the renderer's projection (centers within
    # the silhouette's reach of the image; 1.3 bounds its stretch off-axis)
    _, _, d = camera_coordinates(pos, camera_basis(cam))
    k = pixels_per_unit(cam, HEIGHT)
    reach = 1.3 * k * radius / (1.0 if cam.parallel_projection else d)
    px = project(pos, cam, WIDTH, HEIGHT)
    near_frame = ((px[:, 0] >= -reach) & (px[:, 0] <= WIDTH + reach) & (px[:, 1] >= -reach)
                  & (px[:, 1] <= HEIGHT + reach))
    assert near_frame[keep].all()
    values = np.random.default_rng(0).random(len(pos))
    np.testing.assert_array_equal(
        render(prepare(pos[keep], radius), values[keep], view),
        render(prepare(pos, radius), values, view))

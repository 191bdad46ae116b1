"""Camera conformance: our projection lands on the same pixel as vtkCamera's composite
projection matrix (within 0.5 px), perspective and parallel; rays pass through the pixels."""

import numpy as np
import pytest
from vtkmodules.vtkRenderingCore import vtkCamera

from minority.protocol.projection import camera_basis, project
from minority.protocol.spec import Camera
from minority.render_server.camera import primary_rays

WIDTH, HEIGHT = 640, 480
PIXEL_TOL = 0.5


def vtk_pixels(cam: Camera, points: np.ndarray) -> np.ndarray:
    c = vtkCamera()
    c.SetPosition(*cam.position)
    c.SetFocalPoint(*cam.focal_point)
    c.SetViewUp(*cam.view_up)
    c.SetViewAngle(cam.view_angle_deg)
    c.SetParallelProjection(cam.parallel_projection)
    c.SetParallelScale(cam.parallel_scale_m)
    c.SetClippingRange(0.01, 1000.0)
    m = c.GetCompositeProjectionTransformMatrix(WIDTH / HEIGHT, -1, 1)
    pv = np.array([[m.GetElement(i, j) for j in range(4)] for i in range(4)])
    h = np.c_[points, np.ones(len(points))] @ pv.T
    ndc = h[:, :2] / h[:, 3:4]
    return np.c_[(ndc[:, 0] + 1) * 0.5 * WIDTH, (1 - ndc[:, 1]) * 0.5 * HEIGHT]


def random_cameras(rng, count):
    for _ in range(count):
        position = rng.uniform(-3, 3, 3)
        focal = rng.uniform(-0.5, 0.5, 3)
        up = rng.normal(size=3)
        yield Camera(tuple(position), tuple(focal), tuple(up), rng.uniform(10, 80),
                     bool(rng.random() < 0.5), rng.uniform(0.2, 2.0))


@pytest.mark.parametrize("seed", range(20))
def test_projection_matches_vtk(seed):
    rng = np.random.default_rng(seed)
    for cam in random_cameras(rng, 5):
        b = camera_basis(cam)
        # points in front of the camera, near the focal point
        pts = np.asarray(cam.focal_point) + rng.normal(scale=0.3, size=(200, 3))
        pts = pts[(pts - b.position) @ b.forward > 0.05]
        ours, theirs = project(pts, cam, WIDTH, HEIGHT), vtk_pixels(cam, pts)
        assert np.abs(ours - theirs).max() < PIXEL_TOL


@pytest.mark.parametrize("parallel", [False, True])
def test_rays_go_through_their_pixels(parallel):
    cam = Camera((1.0, -2.0, 0.5), (0.2, 0.1, 0.0), (0, 0, 1), 35.0, parallel, 0.7)
    origins, dirs = primary_rays(cam, WIDTH, HEIGHT)
    assert origins.shape == dirs.shape == (WIDTH * HEIGHT, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    idx = np.random.default_rng(0).integers(0, WIDTH * HEIGHT, 500)
    points = origins[idx] + 1.7 * dirs[idx]
    px = vtk_pixels(cam, points)
    expected = np.c_[idx % WIDTH + 0.5, idx // WIDTH + 0.5]
    assert np.abs(px - expected).max() < 1e-6

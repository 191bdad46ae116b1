"""Rendering a view: background where nothing is hit, colormap colors where spheres are,
shading darker away from the light, shadows only darken, PNG round trip."""

import io

import numpy as np
import pytest
from PIL import Image

from minority.protocol.spec import Camera, View
from minority.render_server.render import encode_png, render_step


def one_sphere_view(**kw) -> View:
    return View("v", Camera((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), (0, 0, 1), 30.0), 96, 64,
                background=(0.0, 0.0, 0.0), field="value", colormap="Grayscale", range=(0.0, 1.0),
                **kw)


def test_single_sphere_image():
    images, times = render_step(np.zeros((1, 3), np.float32), {"value": np.ones(1, np.float32)},
                                0.3, [one_sphere_view()])
    img = images["v"]
    assert img.shape == (64, 96, 3) and img.dtype == np.uint8
    assert (img[0, 0] == 0).all() and (img[-1, -1] == 0).all()  # background corners
    center = img[32, 48].astype(int)
    assert center[0] == center[1] == center[2] > 100  # white sphere (gray map at 1.0), lit
    lit, dark = img[20, 40].astype(int).sum(), img[44, 56].astype(int).sum()
    assert lit > dark  # key light from the upper left
    assert times.setup_s >= 0 and times.render_s > 0


def test_vector_fields_are_colored_by_magnitude():
    fields = {"value": np.array([[0.6, 0.8, 0.0]], np.float32)}  # |v| = 1 -> white
    img = render_step(np.zeros((1, 3), np.float32), fields, 0.3, [one_sphere_view()])[0]["v"]
    assert img[32, 48, 0] == img[32, 48, 2] > 100


def test_shadows_only_darken():
    rng = np.random.default_rng(0)
    pos = rng.random((300, 3)).astype(np.float32) - 0.5
    fields = {"value": np.full(300, 0.8, np.float32)}
    view = one_sphere_view()
    plain = render_step(pos, fields, 0.05, [view])[0]["v"].astype(int)
    shadowed = render_step(pos, fields, 0.05, [view], shadows=True)[0]["v"].astype(int)
    assert (shadowed <= plain).all() and (shadowed < plain).any()


def test_missing_field_is_named():
    with pytest.raises(KeyError, match="needs field 'value'"):
        render_step(np.zeros((1, 3), np.float32), {"other": np.ones(1)}, 0.3, [one_sphere_view()])


def test_png_round_trip():
    img = (np.random.default_rng(0).random((20, 30, 3)) * 255).astype(np.uint8)
    back = np.asarray(Image.open(io.BytesIO(encode_png(img))))
    np.testing.assert_array_equal(back, img)


def test_uhd_image_size():
    view = View("uhd", Camera((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), (0, 0, 1), 30.0), 3840, 2160,
                field="value", colormap="Grayscale", range=(0.0, 1.0))
    images, _ = render_step(np.zeros((3, 3), np.float32), {"value": np.ones(3)}, 0.2, [view])
    assert images["uhd"].shape == (2160, 3840, 3) and images["uhd"].any()


def test_reused_canvas_renders_like_a_fresh_one():
    from minority.render_server.render import Canvas, prepare, render

    rng = np.random.default_rng(3)
    view = one_sphere_view()
    canvas = Canvas(view.width, view.height)
    for _ in range(3):  # different scenes through one canvas
        pos = (rng.random((200, 3)) - 0.5).astype(np.float32)
        scene = prepare(pos, 0.04, grids=False)
        values = rng.random(200)
        reused = render(scene, values, view, canvas=canvas).copy()
        np.testing.assert_array_equal(reused, render(scene, values, view))

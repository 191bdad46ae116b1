"""Annotations on frames (render_server.overlay, through render_server.frames.render_views):
the colorbar follows the colormap, the time text follows the step, the floor and walls are
drawn only where no particle is, `annotations: false` gives the image without annotations, a bad value is
refused by path, and a view's overlay is composed once."""

import json

import jsonschema
import numpy as np
import pytest

import minority.render_server.frames as frames
from minority.protocol.errors import SpecError
from minority.protocol.fields import FIELDS, colour_label
from minority.protocol.schemas import JSON_SCHEMAS
from minority.protocol.spec import Spec
from minority.protocol.view import NO_ANNOTATIONS, Annotations
from minority.render_server import glyphs, overlay
from minority.render_server.assemble import AssembledStep
from minority.render_server.colormap import view_colormap
from minority.render_server.render import Canvas, encode_png, prepare, render

RUN = "overlay-run"
DOMAIN = ((0.0, 0.0, 0.0), (1.0, 0.5, 0.5))  # m: floor z = 0, channel walls y = 0 and 0.5
AERIAL = {"position": [1.6, -1.2, 1.1], "focal_point": [0.5, 0.25, 0.1]}
WIDTH, HEIGHT = 240, 180
ONLY = {  # one annotation at a time
    "colorbar": {"colorbar": True, "time": False, "context": False},
    "time": {"colorbar": False, "time": True, "context": False},
    "context": {"colorbar": False, "time": False, "context": True},
}


def view(name="v", **kw) -> dict:
    return {"name": name, "camera": AERIAL, "width": WIDTH, "height": HEIGHT,
            "field": "displacement", "range": [0.0, 0.4], **kw}


def make_spec(*views) -> Spec:
    return Spec.from_dict({"version": 2, "run": RUN, "views": list(views) or [view()]})


def make_step(n=600, step=20, time_s=0.0125, bounds=DOMAIN, seed=0) -> AssembledStep:
    """A heap of particles on the floor of the back half of the domain (x < 0.5)."""
    rng = np.random.default_rng(seed)
    pos = np.c_[0.5 * rng.random(n), 0.5 * rng.random(n), 0.2 * rng.random(n)]
    fields = {"displacement": (0.3 * rng.random((n, 3))).astype(np.float32)}
    return AssembledStep(step, time_s, pos.astype(np.float32), fields, 0.03, 1, 1, 0, 0.0,
                         False, None, bounds)


def rendered(spec: Spec, step, canvases=None):
    (got,) = frames.render_views(step, spec, {} if canvases is None else canvases)
    assert not got.error
    return got


def plain(step, v) -> tuple[np.ndarray, np.ndarray]:
    """The un-annotated image of `v` and its hit mask [h * w]."""
    canvas = Canvas(v.width, v.height)
    image = render(prepare(step.positions, 0.5 * step.spacing_m, grids=False),
                   step.fields[v.field], v, canvas=canvas).copy()
    return image, canvas.hit.copy()


@pytest.fixture(autouse=True)
def fresh_overlays(monkeypatch):
    """Each test counts its own compositions."""
    cache = overlay.OverlayCache()
    monkeypatch.setattr(frames, "OVERLAYS", cache)
    return cache


def test_annotations_false_is_the_unannotated_image():
    spec = make_spec(view(annotations=False))
    assert spec.views[0].annotations == NO_ANNOTATIONS
    step = make_step()
    got = rendered(spec, step)
    expected, _ = plain(step, spec.views[0])
    np.testing.assert_array_equal(got.image, expected)
    assert got.png == encode_png(expected)
    # the default (no key) annotates: colorbar, time and context all change pixels
    default = rendered(make_spec(view()), step)
    assert (default.image != expected).any(axis=2).sum() > 500


def test_colorbar_follows_the_colormap_from_low_to_high():
    spec = make_spec(view(annotations=ONLY["colorbar"], colormap="Cool to Warm"))
    v = spec.views[0]
    got = rendered(spec, make_step(n=0))  # nothing but the background and the colorbar
    changed = (got.image != 255).any(axis=2)
    cols = np.flatnonzero(changed.any(axis=0))
    assert cols.min() > WIDTH // 2  # at the right, clear of the middle
    # the bar: in the column two pixels in from its frame's right edge, the longest run of
    # changed rows (the title's letters above it are shorter runs), less its frame lines
    column = got.image[:, cols.max() - 2]
    rows = np.flatnonzero(changed[:, cols.max() - 2])
    runs = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1)
    bar = max(runs, key=len)[1:-1]
    assert len(bar) >= 30
    lo, hi = v.range
    frac = (np.arange(len(bar)) + 0.5) / len(bar)  # bottom to top
    expected = view_colormap(v.colormap).map(lo + frac * (hi - lo), lo, hi) * 255.0
    bottom_up = column[bar[::-1]].astype(float)
    np.testing.assert_allclose(bottom_up, expected, atol=1.0)
    assert not np.allclose(bottom_up[0], bottom_up[-1], atol=40)  # blue at 0, red at 0.4


def test_time_text_changes_with_the_step_and_nothing_else_does():
    spec = make_spec(view(annotations=ONLY["time"]))
    first = rendered(spec, make_step(step=20, time_s=0.0125)).image.copy()
    second = rendered(spec, make_step(step=340, time_s=0.2125)).image.copy()
    differ = (first != second).any(axis=2)
    ys, xs = np.nonzero(differ)
    assert len(ys) > 20
    assert ys.max() < HEIGHT // 4 and xs.max() < WIDTH // 2  # the label, top left
    bare = plain(make_step(), spec.views[0])[0]
    np.testing.assert_array_equal(first[HEIGHT // 4:], bare[HEIGHT // 4:])
    assert glyphs.time_label(1652, 0.1951) == "t = 0.195 s · step 1652"


def test_context_is_drawn_on_the_background_and_never_over_particles():
    spec = make_spec(view(annotations=ONLY["context"]))
    v = spec.views[0]
    step = make_step()
    got = rendered(spec, step).image
    bare, hit = plain(step, v)
    drawn = (got != bare).any(axis=2).reshape(-1)
    assert drawn.sum() > 300
    assert not (drawn & hit).any()  # no particle pixel changed
    background = (bare.reshape(-1, 3) == 255).all(axis=1)
    assert background[drawn].all()
    # the composed lines run under the heap too: there the particles hide them
    lines = frames.OVERLAYS.get(v, DOMAIN).context.index
    assert hit[lines].sum() > 50
    # without a domain there is nothing to draw the floor from
    no_domain = rendered(spec, make_step(bounds=None)).image
    np.testing.assert_array_equal(no_domain, bare)


def test_context_lines_lie_on_the_floor_and_the_channel_walls():
    v = make_spec(view()).views[0]
    lines = overlay.context_segments(v, DOMAIN)
    assert [alpha for _, alpha in lines] == [overlay.GRID_ALPHA, overlay.EDGE_ALPHA]
    (lo, hi) = np.array(DOMAIN)
    for segments, _ in lines:
        on_floor = np.isclose(segments[:, :, 2], lo[2]).all(axis=1)
        on_wall = (np.isclose(segments[:, :, 1], lo[1]).all(axis=1)
                   | np.isclose(segments[:, :, 1], hi[1]).all(axis=1))
        assert (on_floor | on_wall).all()
    grid = lines[0][0]
    # the camera (y = -1.2, z = 1.1) sees the floor and the far wall y = 0.5 from inside, the
    # near wall y = 0 from outside: grid lines on the first two only
    assert np.isclose(grid[:, :, 2], 0.0).all(axis=1).sum() > 5
    assert np.isclose(grid[:, :, 1], 0.5).all(axis=1).sum() > 5
    assert not np.isclose(grid[:, :, 1], 0.0).all(axis=1).any()
    assert len(lines[1][0]) == 12  # the three faces' outlines
    boxed = make_spec(view(annotations={"bbox": True, "context": False})).views[0]
    ((box, alpha),) = overlay.context_segments(boxed, DOMAIN)
    assert alpha == overlay.BBOX_ALPHA and len(box) == 12
    ends = {tuple(sorted(map(tuple, e.tolist()))) for e in box}
    assert len(ends) == 12  # the box's 12 edges, each once, between its 8 corners
    assert {c for e in ends for c in e} == {(x, y, z) for x in (lo[0], hi[0])
                                            for y in (lo[1], hi[1]) for z in (lo[2], hi[2])}


def test_bbox_is_off_by_default_and_draws_when_asked():
    step = make_step(n=0)
    context = rendered(make_spec(view(annotations=ONLY["context"])), step).image
    boxed = rendered(make_spec(view(annotations={**ONLY["context"], "bbox": True})), step).image
    assert (context != boxed).any(axis=2).sum() > 100


def test_the_overlay_is_composed_once_per_view(fresh_overlays):
    spec = make_spec(view("a"), view("b", colormap="Grayscale"),
                     view("a-again", schedule=[{"every_steps": 10}]))
    canvases = {}
    for k in range(4):
        frames.render_views(make_step(step=20 * (k + 1), time_s=0.01 * k, seed=k), spec,
                            canvases)
    # "a-again" draws like "a" (its name and schedule do not show): 2 compositions
    assert fresh_overlays.composed == 2
    wider = make_spec(view("a", range=[0.0, 0.8]))
    frames.render_views(make_step(), wider, canvases)
    assert fresh_overlays.composed == 3  # another range, another colorbar
    frames.render_views(make_step(bounds=((0, 0, 0), (2.0, 0.5, 0.5))), wider, canvases)
    assert fresh_overlays.composed == 4  # another domain


@pytest.mark.parametrize(("value", "message"), [
    ("yes", r"views\[0\]\.annotations: expected bool \| object, got str"),
    ({"colorbar": 1}, r"views\[0\]\.annotations\.colorbar: expected bool, got int"),
    ({"colourbar": True}, r"views\[0\]\.annotations: unknown field\(s\) colourbar"),
    (None, r"views\[0\]\.annotations: expected bool \| object, got null"),
])
def test_a_bad_annotations_value_is_refused_by_path(value, message):
    with pytest.raises(SpecError, match=message):
        make_spec(view(annotations=value))


def test_annotations_in_a_spec_round_trip_and_validate():
    schema = jsonschema.Draft202012Validator(JSON_SCHEMAS["minority.Spec"])
    for given, expected in [(True, Annotations()), (False, NO_ANNOTATIONS),
                            ({"bbox": True}, Annotations(bbox=True)),
                            ({"time": False}, Annotations(time=False))]:
        spec = make_spec(view(annotations=given))
        assert spec.views[0].annotations == expected
        d = spec.to_dict()
        assert Spec.from_dict(json.loads(json.dumps(d))) == spec
        # the default is not written: a spec without the key encodes as before
        assert ("annotations" in d["views"][0]) == (expected != Annotations())
        assert schema.is_valid(d)
    bad = make_spec().to_dict()
    bad["views"][0]["annotations"] = {"bbox": "no"}
    assert not schema.is_valid(bad)


def test_field_units_label_the_colorbar():
    assert colour_label("displacement") == "displacement magnitude (m)"
    assert colour_label("velocity_magnitude") == "velocity magnitude (m/s)"
    assert colour_label("pressure") == "pressure (Pa)"
    assert colour_label("id") == "id"
    assert colour_label("temperature") == "temperature"  # not in the table: its name
    assert {"displacement", "velocity", "pressure", "id"} <= FIELDS.keys()


def test_small_images_get_no_text_and_a_bad_image_is_refused():
    tiny = make_spec(view(width=64, height=48)).views[0]
    made = overlay.compose(tiny, DOMAIN)
    assert made.time is None and len(made.legend.index) == 0 and len(made.context.index) > 0
    with pytest.raises(ValueError, match="overlay of 64x48 px applied to an image"):
        overlay.apply(made, np.zeros((48, 65, 3), np.uint8), None, 0, 0.0)

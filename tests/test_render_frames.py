"""Rendering the due views of a step (render_server.frames): each view shows only the
particles of its window's regions, decimated by id; one acceleration structure per distinct
subset; inline colormaps; every_s cadences decided with the previous step's time."""

import dataclasses

import numpy as np
import pytest

import minority.render_server.frames as frames
from minority.protocol.errors import SpecError
from minority.protocol.spec import InlineColormap, Spec, inside_mask
from minority.render_server.assemble import AssembledStep
from minority.render_server.colormap import preset, view_colormap
from minority.render_server.render import prepare, render

RUN = "frames-run"
CAMERA = {"position": [0.5, -2.0, 0.5], "focal_point": [0.5, 0.5, 0.5]}
LEFT = {"name": "left", "lo_m": [0.0, 0.0, 0.0], "hi_m": [0.5, 1.0, 1.0]}
CORNER = {"name": "corner", "lo_m": [0.6, 0.0, 0.6], "hi_m": [1.0, 1.0, 1.0]}
EMPTY = {"name": "empty", "lo_m": [5.0, 5.0, 5.0], "hi_m": [6.0, 6.0, 6.0]}


def view(name, **kw) -> dict:
    # annotations off: these tests compare the particles drawn (tests/test_overlay.py: the rest)
    return {"name": name, "camera": CAMERA, "width": 48, "height": 40, "field": "value",
            "range": [0, 1], "annotations": False, **kw}


def make_spec(*views, regions=(LEFT, CORNER, EMPTY)) -> Spec:
    return Spec.from_dict({"version": 2, "run": RUN, "views": list(views),
                           "regions": list(regions)})


def make_step(n=400, step=20, time_s=0.002, prev_time_s=None, ids=True, seed=1) -> AssembledStep:
    rng = np.random.default_rng(seed)
    fields = {"value": rng.random(n, dtype=np.float32),
              "vector": rng.random((n, 3), dtype=np.float32)}
    if ids:
        fields["id"] = rng.permutation(n).astype(np.int64)
    return AssembledStep(step, time_s, rng.random((n, 3), dtype=np.float32), fields, 0.02,
                         1, 1, 0, 0.0, False, prev_time_s)


def direct(step, spec, v, rows) -> np.ndarray:
    """The image of `v` rendered straight from the given rows of the step."""
    scene = prepare(step.positions[rows], 0.5 * step.spacing_m, grids=False)
    return render(scene, step.fields[v.field][rows], v).copy()


def by_name(results):
    return {r.view.name: r for r in results}


def test_each_view_shows_its_regions_and_subsets_are_prepared_once(monkeypatch):
    spec = make_spec(view("left", schedule=[{"regions": ["left"]}]),
                     view("left-too", schedule=[{"regions": ["left"]}], colormap="Grayscale"),
                     view("two", schedule=[{"regions": ["left", "corner"]}]),
                     view("all"))
    step = make_step()
    calls = []
    monkeypatch.setattr(frames, "prepare", lambda pos, *a, **k: calls.append(len(pos))
                        or prepare(pos, *a, **k))
    got = by_name(frames.render_views(step, spec, {}))
    assert len(calls) == 3  # left, left + corner, everything
    left = inside_mask(step.positions, (spec.region("left"),))
    two = left | inside_mask(step.positions, (spec.region("corner"),))
    assert 0 < left.sum() < two.sum() < len(step.positions)
    for name, rows in [("left", left), ("left-too", left), ("two", two),
                       ("all", np.ones(len(left), bool))]:
        np.testing.assert_array_equal(got[name].image, direct(step, spec, got[name].view, rows))
        assert got[name].particles == rows.sum()
    assert got["left"].setup_s == got["left-too"].setup_s  # one build, charged to both
    assert not np.array_equal(got["left"].image, got["all"].image)


def test_decimation_by_id_and_without_ids():
    spec = make_spec(view("third", decimate=3), view("all"))
    step = make_step()
    got = by_name(frames.render_views(step, spec, {}))
    rows = step.fields["id"] % 3 == 0
    np.testing.assert_array_equal(got["third"].image, direct(step, spec, got["third"].view, rows))
    assert got["third"].particles == rows.sum()
    # no ids: the sim decimated already, the view draws what arrived
    plain = make_step(ids=False)
    got = by_name(frames.render_views(plain, spec, {}))
    np.testing.assert_array_equal(got["third"].image, got["all"].image)


def test_inline_colormap_renders_like_the_named_preset():
    viridis = preset("Viridis (matplotlib)")
    inline = InlineColormap(name="my viridis", color_space=viridis.color_space,
                            rgb_points=viridis.rgb_points, nan_color=viridis.nan_color)
    spec = make_spec(view("named", field="vector"),
                     view("inline", field="vector", colormap=inline.to_dict()))
    assert spec.views[1].colormap == inline
    got = by_name(frames.render_views(make_step(), spec, {}))
    np.testing.assert_array_equal(got["named"].image, got["inline"].image)
    assert view_colormap(inline) is view_colormap(inline)  # built once
    np.testing.assert_array_equal(view_colormap(inline).lut(), viridis.lut())


@pytest.mark.parametrize(("time_s", "prev_time_s", "due"), [
    (0.0105, 0.0095, True),  # the instant 0.01 s lies in (prev, t]
    (0.0115, 0.0105, False),
    (0.0100, 0.0095, True),
    (0.0105, None, False),  # without the previous time only exact instants are due
])
def test_every_s_cadence_uses_the_previous_step_time(time_s, prev_time_s, due):
    spec = make_spec(view("timed", schedule=[{"every_s": 0.005}]))
    step = make_step(step=7, time_s=time_s, prev_time_s=prev_time_s)
    assert [r.view.name for r in frames.render_views(step, spec, {})] == (["timed"] if due else [])


def test_empty_region_shows_the_background_and_what_cannot_render_is_named():
    with pytest.raises(SpecError, match=r"views\[0\].colormap: 'No Such Preset' is neither"):
        make_spec(view("unknown", colormap="No Such Preset"))
    spec = make_spec(view("nothing", schedule=[{"regions": ["empty"]}], background=[0, 0, 1]),
                     view("pressure", field="pressure"), view("all"), view("unknown"))
    # a view made in code is not checked: the renderer names what it cannot draw
    unknown = dataclasses.replace(spec.views[-1], colormap="No Such Preset")
    spec = dataclasses.replace(spec, views=(*spec.views[:-1], unknown))
    got = by_name(frames.render_views(make_step(), spec, {}))
    assert got["nothing"].particles == 0 and (got["nothing"].image == [0, 0, 255]).all()
    assert got["pressure"].image is None and "needs field 'pressure'" in got["pressure"].error
    assert got["all"].image is not None and not got["all"].error
    assert "'No Such Preset' is neither a built-in ParaView preset" in got["unknown"].error
    # a step whose chunks hold no particles: each due view that can render is its background
    empty = by_name(frames.render_views(make_step(n=0), spec, {}))
    assert empty["all"].particles == 0 and (empty["all"].image == 255).all()
    assert empty["nothing"].particles == 0 and "needs field" in empty["pressure"].error


def test_canvases_are_reused_per_view():
    spec = make_spec(view("all"))
    canvases = {}
    first = frames.render_views(make_step(seed=1), spec, canvases)[0].png
    canvas = canvases["all"]
    second = frames.render_views(make_step(seed=2), spec, canvases)
    assert canvases["all"] is canvas and second[0].png != first

"""Spec validation names the bad field; files and wire round-trip."""

import copy
import json
import math

import pytest
from conftest import make_spec

from minority.protocol import Spec, SpecError, View, Window


def base() -> dict:
    return make_spec().to_dict()


def with_change(path: str, value):
    d = copy.deepcopy(base())
    *parents, last = path.split(".")
    node = d
    for p in parents:
        node = node[int(p)] if p.isdigit() else node[p]
    if value is KeyError:
        del node[last]
    else:
        node[last] = value
    return d


_INLINE = {"Name": "two", "ColorSpace": "RGB", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]}


@pytest.mark.parametrize("path,value,message", [
    ("version", 3, "version: spec version 3 is not supported"),
    ("run", "a/b", "run: expected"),
    ("views", [], r"views: expected array of length >= 1, got \[\]"),
    ("views.0.name", "", r"views\[0\].name"),
    ("views.1.name", "side", "view names must be unique"),
    ("views.0.camera.position", [0, 0], r"views\[0\].camera.position: expected array of length 3, got 2"),
    ("views.0.camera.focal_point", [0, float("nan"), 0], r"views\[0\].camera.focal_point\[1\]"),
    ("views.0.camera.view_up", [0, 2.25, -0.1], r"views\[0\].camera.view_up: parallel"),
    ("views.0.camera.position", [0.5, 0.25, 0.1], r"views\[0\].camera: position and focal_point"),
    ("views.0.camera.view_angle_deg", 180, r"views\[0\].camera.view_angle_deg"),
    ("views.1.camera.parallel_scale_m", 0, r"views\[1\].camera.parallel_scale_m"),
    ("views.0.camera", KeyError, r"views\[0\]: missing camera"),
    ("views.0.width", 0, r"views\[0\].width: expected int >= 1, got 0"),
    ("views.0.height", 10000, r"views\[0\].height"),
    ("views.0.range", [1.0, 0.5], r"views\[0\].range: lower bound"),
    ("views.0.background", [1, 1, 2], r"views\[0\].background"),
    ("views.0.decimate", 0, r"views\[0\].decimate: expected int >= 1, got 0"),
    ("views.0.colormap", 7, r"views\[0\].colormap: expected str \| object, got int"),
    ("views.0.colormap", {**_INLINE, "ColorSpace": "CMYK"}, r"views\[0\].colormap.ColorSpace"),
    ("views.0.colormap", {**_INLINE, "RGBPoints": [0, 0, 0, 0, 1, 1, 1]},
     r"views\[0\].colormap.RGBPoints: expected array of length >= 8"),
    ("views.0.colormap", {**_INLINE, "RGBPoints": [1, 0, 0, 0, 0, 1, 1, 1]},
     r"views\[0\].colormap.RGBPoints\[4\]: x 0.0 is below the previous x 1.0"),
    ("views.0.colormap", {**_INLINE, "RGBPoints": [0, 0, 0, 0, 1, 1, 2, 1]},
     r"views\[0\].colormap.RGBPoints\[6\]: color component 2.0 is outside \[0, 1\]"),
    ("views.0.colormap", {"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]}, r"views\[0\].colormap: missing Name"),
    ("views.0.schedule", [], r"views\[0\].schedule: expected array of length >= 1, got \[\]"),
    ("views.0.schedule.0.t_end_s", -1, r"views\[0\].schedule\[0\].t_end_s"),
    ("views.0.schedule.0.every_steps", 0, r"views\[0\].schedule\[0\].every_steps"),
    ("views.0.schedule.0.every_s", 0, r"views\[0\].schedule\[0\].every_s"),
    ("views.0.schedule.0.every_s", 0.01, r"views\[0\].schedule\[0\]: give every_steps or every_s"),
    ("views.0.schedule.0.when", 1, r"views\[0\].schedule\[0\]: unknown field\(s\) when"),
    ("views.0.t_start_s", 0.0, r"views\[0\]: give a schedule or the single-window keys"),
    ("views.0.colour", "red", r"views\[0\]: unknown field\(s\) colour"),
    ("sphere_radius_m", 0, r"sphere_radius_m: expected float >= 1e-09, got 0"),
    ("regions", {"name": "a"}, "regions: expected array, got object"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 0]}], r"regions\[0\]: missing hi_m"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 1], "hi_m": [1, 1, 0]}],
     r"regions\[0\]: lo_m \[0.0, 0.0, 1.0\] exceeds hi_m"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}] * 2,
     "region names must be unique"),
    ("views.0.schedule.0.regions", "front", r"views\[0\].schedule\[0\].regions: expected array, got str"),
    ("views.0.schedule.0.regions", ["nowhere"],
     r"views\[0\].schedule\[0\].regions\[0\]: no region named 'nowhere'"),
    ("events", [{"name": "onset"}], r"events\[0\]: missing time_s"),
    ("events", [{"name": "onset", "time_s": -0.1}], r"events\[0\].time_s: expected float >= 0.0, got -0.1"),
    ("events", [{"name": "onset", "time_s": 0.1, "tolerance_s": float("inf")}],
     r"events\[0\].tolerance_s"),
    ("events", [{"name": "onset", "time_s": 0.1}] * 2, "event names must be unique"),
    ("budget", {"frames": 0}, r"budget.frames: expected int >= 1, got 0"),
    ("budget", {"frames": 10, "pixels": 3}, r"budget: unknown field\(s\) pixels"),
    ("budget", {"bytes": 1.5}, r"budget.bytes: expected int \| null, got float"),
    ("provenance", [1], "provenance: expected object, got array"),
    ("views.0.colormap", "No Such Preset",
     r"views\[0\].colormap: 'No Such Preset' is neither a built-in ParaView preset"),
    ("views.0.colormap", "Viridis", r"views\[0\].colormap: 'Viridis' is neither"),  # names exact
    ("spec_key", 1, r"^spec: unknown field\(s\) spec_key"),
    ("run", KeyError, r"^spec: missing run"),
])
def test_bad_spec_names_the_field(path, value, message):
    with pytest.raises(SpecError, match=message):
        Spec.from_dict(with_change(path, value))


def test_file_and_wire_round_trip(tmp_path):
    spec = make_spec()
    spec.save(tmp_path / "spec.json")
    assert Spec.load(tmp_path / "spec.json") == spec
    assert math.isinf(spec.views[1].t_end_s)


def test_sphere_radius_round_trips():
    d = base()
    d["sphere_radius_m"] = 0.004
    spec = Spec.from_dict(d)
    assert spec.sphere_radius_m == 0.004 and Spec.from_dict(spec.to_dict()) == spec
    assert make_spec().sphere_radius_m is None and "sphere_radius_m" not in make_spec().to_dict()


def test_a_bad_field_in_a_file_names_the_file_and_the_field(tmp_path):
    (tmp_path / "s.json").write_text(json.dumps(with_change("views.0.colormap", "Jett")))
    with pytest.raises(SpecError, match=rf"^{tmp_path / 's.json'}: views\[0\].colormap: 'Jett'"):
        Spec.load(tmp_path / "s.json")


def test_bad_json_file(tmp_path):
    (tmp_path / "s.json").write_text("{views: ")
    with pytest.raises(SpecError, match="not valid JSON"):
        Spec.load(tmp_path / "s.json")


def test_schedule_and_fields():
    spec = make_spec()
    assert [v.name for v in spec.wants(20, 0.1)] == ["side"]
    assert [v.name for v in spec.wants(21, 0.1)] == []
    assert [v.name for v in spec.wants(40, 0.2)] == ["top"]
    assert spec.fields == ("displacement", "velocity_magnitude")


def test_shipped_example_spec_loads():
    from pathlib import Path

    spec = Spec.load(Path(__file__).parent.parent / "deploy" / "spec-column.json")
    assert [v.name for v in spec.views] == ["side", "top", "aerial"]
    assert spec.fields == ("displacement",)
    assert [v.name for v in spec.wants(20, 0.01)] == ["side"]
    assert [v.name for v in spec.wants(4000, 0.5)] == ["top", "aerial"]


def with_regions() -> Spec:
    d = base()
    d["regions"] = [{"name": "column", "lo_m": [0.0, 0.0, 0.0], "hi_m": [0.2, 0.5, 0.5]},
                    {"name": "front", "lo_m": [0.3, 0.0, 0.0], "hi_m": [1.0, 0.5, 0.1]}]
    d["views"][0]["schedule"][0]["regions"] = ["column", "front"]
    d["views"][1]["schedule"][0]["regions"] = ["front"]
    return Spec.from_dict(d)


def test_regions_round_trip(tmp_path):
    spec = with_regions()
    spec.save(tmp_path / "spec.json")
    assert Spec.load(tmp_path / "spec.json") == spec
    assert [r.name for r in spec.regions] == ["column", "front"]
    assert spec.views[1].regions == ("front",)
    plain = make_spec().to_dict()  # no regions anywhere: windows name none
    assert plain["regions"] == [] and all("regions" not in w for v in plain["views"]
                                          for w in v["schedule"])


def test_request_unions_the_scheduled_views():
    spec = make_spec()  # views without regions: every particle
    req = spec.request(20, 0.1)
    assert req.views == ("side",) and req.fields == ("displacement",) and req.regions is None
    assert spec.request(21, 0.1) is None
    spec = with_regions()
    req = spec.request(20, 0.1)
    assert req.fields == ("displacement",) and [r.name for r in req.regions] == ["column", "front"]
    req = spec.request(40, 0.2)
    assert req.fields == ("velocity_magnitude",) and [r.name for r in req.regions] == ["front"]
    d = with_regions().to_dict()
    d["views"][0]["schedule"][0]["t_end_s"] = None  # both views at step 40, t = 0.2 s: union
    del d["views"][1]["schedule"][0]["regions"]  # ... and one of them needs every particle
    req = Spec.from_dict(d).request(40, 0.2)
    assert req.fields == ("displacement", "velocity_magnitude") and req.regions is None


def test_shipped_example_spec_requests_every_particle():
    from pathlib import Path

    spec = Spec.load(Path(__file__).parent.parent / "deploy" / "spec-column.json")
    assert spec.regions == () and spec.request(20, 0.01).regions is None


def test_version_1_file_reads_as_one_window_per_view():
    spec = make_spec()  # conftest writes it in the version 1 form
    side, top = spec.views
    assert spec.version == 2 and spec.to_dict()["version"] == 2
    assert side.schedule == (Window(0.0, 0.15, 20),) and top.schedule == (Window(0.15),)
    assert Spec.from_dict(spec.to_dict()) == spec


def test_every_s_cadence_fires_on_the_first_step_after_each_instant():
    w = Window(0.1, 0.31, every_s=0.05)
    dt = 0.012
    times = [0.0]
    for _ in range(40):
        times.append(times[-1] + dt)  # as the simulation accumulates time
    due = [round(t, 6) for k, t in enumerate(times[1:], 1) if w.wants(k, t, times[k - 1])]
    # instants 0.10, 0.15, ..., 0.30: the first step time at or after each one
    assert due == [0.108, 0.156, 0.204, 0.252, 0.3]
    assert w.planned_frames(1.0, dt) == 5
    assert not w.wants(0, 0.0) and Window(every_s=0.05).wants(0, 0.0)
    # steps that land on the instants (to rounding) still render each instant once
    times = [0.0]
    for _ in range(40):
        times.append(times[-1] + 0.01)
    assert sum(w.wants(k, t, times[k - 1]) for k, t in enumerate(times[1:], 1)) == 5


def test_every_s_cadence_renders_the_instant_at_the_window_end():
    """The instant t_end_s falls to the first step after it, whose time is past the window:
    it is still due (once), so a window renders all of planned_frames."""
    w = Window(0.1, 0.3, every_s=0.05)  # (0.3 - 0.1) / 0.05 = 3.9999999999999996
    times = [0.014 * k for k in range(40)]
    due = [round(t, 6) for k, t in enumerate(times[1:], 1) if w.wants(k, t, times[k - 1])]
    assert due == [0.112, 0.154, 0.21, 0.252, 0.308]
    assert len(due) == w.planned_frames(1.0, 0.014) == 5
    assert not w.wants(23, 0.322, 0.308)  # after the last instant
    assert [w.instant(t) for t in (0.05, 0.1, 0.29, 0.308)] == [-1, 0, 3, 4]


def test_schedule_with_several_windows_and_regions():
    d = base()
    d["regions"] = [{"name": "near", "lo_m": [0, 0, 0], "hi_m": [0.2, 1, 1]},
                    {"name": "far", "lo_m": [0.2, 0, 0], "hi_m": [1, 1, 1]}]
    d["views"][0]["schedule"] = [
        {"t_start_s": 0.0, "t_end_s": 0.1, "every_s": 0.05, "regions": ["near"]},
        {"t_start_s": 0.1, "t_end_s": 0.5, "every_steps": 10, "regions": ["far"]}]
    spec = Spec.from_dict(d)
    side = spec.views[0]
    assert side.t_start_s == 0.0 and side.t_end_s == 0.5 and side.regions == ("near", "far")
    assert [r.name for r in spec.view_regions(side, 50, 0.05, 0.049)] == ["near"]
    assert spec.view_regions(side, 50, 0.05, 0.049) == spec.request(50, 0.05, 0.049).regions
    assert spec.request(51, 0.051, 0.05) is None
    assert [r.name for r in spec.request(210, 0.2, 0.199).regions] == ["far"]
    # the top view (every particle) opens at 0.15 s: no cull at a step both want
    assert spec.request(400, 0.4, 0.399).regions is None
    assert [r.name for r in spec.active_regions(0.12)] == ["far"]
    assert spec.active_regions(0.3) is None and spec.active_regions(0.2) is None
    d["views"][1]["schedule"][0]["t_end_s"] = 0.6
    assert Spec.from_dict(d).active_regions(0.7) == ()


def test_decimation_requests_the_common_stride_and_ids_when_views_differ():
    d = base()
    d["views"][0]["schedule"][0]["t_end_s"] = None
    d["views"][1]["schedule"][0]["every_steps"] = 20
    d["views"][0]["decimate"], d["views"][1]["decimate"] = 4, 6
    req = Spec.from_dict(d).request(40, 0.2)
    assert req.decimate == 2 and req.fields == ("displacement", "velocity_magnitude", "id")
    d["views"][1]["decimate"] = 4
    req = Spec.from_dict(d).request(40, 0.2)
    assert req.decimate == 4 and "id" not in req.fields
    assert Spec.from_dict(d).request(20, 0.1).decimate == 4  # side alone


def test_events_budget_provenance_and_inline_colormap_round_trip(tmp_path):
    d = base()
    d["events"] = [{"name": "onset", "time_s": 0.05, "tolerance_s": 0.01},
                   {"name": "runout_end", "time_s": 0.6}]
    d["budget"] = {"frames": 120, "bytes": None}
    d["provenance"] = {"checkpoint": "column_l64_m5.pt"}
    d["views"][0]["colormap"] = _INLINE
    spec = Spec.from_dict(d)
    spec.save(tmp_path / "s.json")
    again = Spec.load(tmp_path / "s.json")
    assert again == spec and again.provenance == {"checkpoint": "column_l64_m5.pt"}
    assert [e.name for e in spec.events] == ["onset", "runout_end"]
    assert spec.events[1].tolerance_s == 0.0 and spec.budget.frames == 120
    assert spec.views[0].colormap.rgb_points == (0, 0, 0, 0, 1, 1, 1, 1)
    assert spec.planned_frames(0.3, 0.001) == (150 // 20 + 1) + (150 // 20 + 1)


@pytest.mark.parametrize("name", ["Cool to Warm", "Viridis (matplotlib)", "Turbo", "viridis",
                                  "coolwarm", "RdBu_r", "gray"])
def test_a_paraview_or_matplotlib_colormap_name_is_accepted(name):
    spec = Spec.from_dict(with_change("views.0.colormap", name))
    assert spec.views[0].colormap == name and Spec.from_dict(spec.to_dict()) == spec


def test_the_one_window_shorthand_names_the_view_in_errors():
    d = base()
    view = {k: v for k, v in d["views"][0].items() if k != "schedule"}
    d["views"][0] = {**view, "t_start_s": 0.1, "every_steps": 0}
    with pytest.raises(SpecError, match=r"^views\[0\].every_steps: expected int >= 1, got 0"):
        Spec.from_dict(d)
    d["views"][0] = {**view, "t_start_s": 0.1, "every_steps": 5}
    assert Spec.from_dict(d).views[0].schedule == (Window(t_start_s=0.1, every_steps=5),)
    assert d["views"][0]["t_start_s"] == 0.1  # the caller's object is left as it was
    for bad, message in (({**view, "every_steps": 0}, r"^v\.every_steps: expected int >= 1, got 0"),
                         ({**view, "every_s": 1.0, "schedule": [{}]},
                          r"^v: give a schedule or the single-window keys \(every_s\)")):
        with pytest.raises(SpecError, match=message):
            View.from_dict(bad, "v")  # one view alone, as a file's views[i]


def test_numbers_that_json_cannot_hold_are_refused_from_python_objects_too():
    for value in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(SpecError, match=r"views\[0\].camera.position\[0\]: expected a "
                                            r"finite number"):
            Spec.from_dict(with_change("views.0.camera.position", [value, 0.0, 0.0]))


def test_what_to_dict_writes_reads_back_through_the_document_types():
    """The model's JSON and the document types (the decoder, the stored schema) agree."""
    import msgspec

    from minority.protocol.spec import SpecDocument

    d = base()
    d["views"][0]["colormap"] = dict(_INLINE)
    d["regions"] = [{"name": "toe", "lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}]
    d["views"][0]["schedule"] = [{"t_start_s": 0.0, "t_end_s": None, "every_s": 0.01,
                                  "regions": ["toe"]}]
    d["events"] = [{"name": "onset", "time_s": 0.1, "tolerance_s": 0.01}]
    d["budget"] = {"frames": 10, "bytes": None}
    spec = Spec.from_dict(d)
    doc = msgspec.convert(spec.to_dict(), SpecDocument)
    assert Spec.from_document(doc) == spec  # and convert refused no key to_dict wrote

"""Spec validation names the bad field; files and wire round-trip."""

import copy
import math

import pytest
from conftest import make_spec

from protocol import Spec, SpecError


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


@pytest.mark.parametrize("path,value,message", [
    ("version", 2, "version: spec version 2 is not supported"),
    ("run", "a/b", "run: expected"),
    ("views", [], "views: expected a non-empty list"),
    ("views.0.name", "", r"views\[0\].name"),
    ("views.1.name", "side", "view names must be unique"),
    ("views.0.camera.position", [0, 0], r"views\[0\].camera.position: expected a list of 3"),
    ("views.0.camera.focal_point", [0, float("nan"), 0], r"views\[0\].camera.focal_point\[1\]"),
    ("views.0.camera.view_up", [0, 2.25, -0.1], r"views\[0\].camera.view_up: parallel"),
    ("views.0.camera.position", [0.5, 0.25, 0.1], r"views\[0\].camera: position and focal_point"),
    ("views.0.camera.view_angle_deg", 180, r"views\[0\].camera.view_angle_deg"),
    ("views.1.camera.parallel_scale_m", 0, r"views\[1\].camera.parallel_scale_m"),
    ("views.0.camera", KeyError, r"views\[0\]: missing camera"),
    ("views.0.width", 0, r"views\[0\].width: 0 is outside"),
    ("views.0.height", 10000, r"views\[0\].height"),
    ("views.0.range", [1.0, 0.5], r"views\[0\].range: lower bound"),
    ("views.0.background", [1, 1, 2], r"views\[0\].background"),
    ("views.0.t_end_s", -1, r"views\[0\].t_end_s"),
    ("views.0.every_steps", 0, r"views\[0\].every_steps"),
    ("views.0.colour", "red", r"views\[0\]: unknown field\(s\) colour"),
    ("sphere_radius_m", 0, r"sphere_radius_m: 0 is outside"),
    ("regions", {"name": "a"}, "regions: expected a list"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 0]}], r"regions\[0\]: missing hi_m"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 1], "hi_m": [1, 1, 0]}],
     r"regions\[0\]: lo_m \[0.0, 0.0, 1.0\] exceeds hi_m"),
    ("regions", [{"name": "a", "lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}] * 2,
     "region names must be unique"),
    ("views.0.regions", "front", r"views\[0\].regions: expected a list"),
    ("views.0.regions", ["nowhere"], r"views\[0\].regions\[0\]: no region named 'nowhere'"),
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
    d["views"][0]["regions"] = ["column", "front"]
    d["views"][1]["regions"] = ["front"]
    return Spec.from_dict(d)


def test_regions_round_trip_and_old_specs_write_as_before(tmp_path):
    spec = with_regions()
    spec.save(tmp_path / "spec.json")
    assert Spec.load(tmp_path / "spec.json") == spec
    assert [r.name for r in spec.regions] == ["column", "front"]
    assert spec.views[1].regions == ("front",)
    plain = make_spec().to_dict()  # no regions anywhere: no new keys in the JSON
    assert "regions" not in plain and all("regions" not in v for v in plain["views"])


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
    d["views"][0]["t_end_s"] = None  # both views at step 40, t = 0.2 s: union of both
    del d["views"][1]["regions"]  # ... and one of them needs every particle
    req = Spec.from_dict(d).request(40, 0.2)
    assert req.fields == ("displacement", "velocity_magnitude") and req.regions is None


def test_shipped_example_spec_requests_every_particle():
    from pathlib import Path

    spec = Spec.load(Path(__file__).parent.parent / "deploy" / "spec-column.json")
    assert spec.regions == () and spec.request(20, 0.01).regions is None

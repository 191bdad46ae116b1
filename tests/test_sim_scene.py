"""Scene loading: shipped scenes, particle counts, errors that name the bad key."""

import pytest

from minority.sim.columns import ColumnSpec, channel_column_toml
from minority.sim.scene import SCENES_DIR, SceneError, Shape, builtin_scene_path, load_scene, loads_scene
from minority.sim.state import seed_particles

SHIPPED_COUNTS = {"tiny": 400, "cylinder_small": 1344, "column_13k": 12_960,
                  "column_100k": 103_680}


@pytest.mark.parametrize("name,count", sorted(SHIPPED_COUNTS.items()))
def test_shipped_scene_particle_counts(name, count):
    scene = load_scene(builtin_scene_path(name))
    assert seed_particles(scene).n == count


def test_all_shipped_scenes_load():
    names = sorted(p.stem for p in SCENES_DIR.glob("*.toml"))
    assert {"tiny", "cylinder_small", "column_13k", "column_100k", "column_1m"} <= set(names)
    for name in names:
        scene = load_scene(builtin_scene_path(name))
        assert scene.toml_text
    big = load_scene(builtin_scene_path("column_1m"))
    # 72 x 72 x 160 lattice points fill the 0.144 x 0.144 x 0.32 m column
    assert big.particle_spacing_m == pytest.approx(0.002)
    assert big.bodies[0].shape is Shape.BOX


def test_cylinder_is_round():
    scene = load_scene(builtin_scene_path("cylinder_small"))
    ps = seed_particles(scene)
    r = ((ps.x[:, 0] - 0.24) ** 2 + (ps.x[:, 1] - 0.24) ** 2) ** 0.5
    assert r.max() <= 0.06
    assert r.max() > 0.05


@pytest.mark.parametrize("old,new,key", [
    ("density_kg_m3 = 1800.0", "density_kg_m3 = -1.0", "material.density_kg_m3"),
    ("poisson_ratio = 0.3", "poisson_ratio = 0.5", "material.poisson_ratio"),
    ("friction_angle_deg = 30.0", "friction_angle_deg = 95.0", "material.friction_angle_deg"),
    ("friction_angle_deg = 30.0", "friction_angle = 30.0", "material.friction_angle"),
    ('shape = "box"', 'shape = "sphere"', "body[0].shape"),
    ("cell_size_m = 0.02", "cell_size_m = 0.03", "domain.size_m"),
    ("cell_size_m = 0.02", 'cell_size_m = "fine"', "domain.cell_size_m"),
    ("duration_s = 0.2", "duration_s = 0.0", "time.duration_s"),
    ("cfl = 0.3", "cfl = 0.9", "time.cfl"),
    ("flip = 0.99", "flip = 1.5", "numerics.flip"),
    ("flip = 0.99", "flip_ratio = 0.99", "numerics.flip_ratio"),
    ("per_cell_per_axis = 2", "per_cell_per_axis = 2.5", "particles.per_cell_per_axis"),
    ("hi_m = [0.1, 0.04, 0.1]", "hi_m = [0.5, 0.04, 0.1]", "body[0].hi_m"),
    ("y_min = 0.0", "y_min = -0.1", "boundary.y_min"),
])
def test_scene_error_names_key(old, new, key):
    text = channel_column_toml(ColumnSpec())
    assert old in text
    with pytest.raises(SceneError, match=key.replace("[", r"\[").replace("]", r"\]")):
        loads_scene(text.replace(old, new))


def test_scene_error_is_value_error_and_missing_table():
    with pytest.raises(ValueError, match="domain"):
        loads_scene('name = "x"\n')
    with pytest.raises(SceneError, match="invalid TOML"):
        loads_scene("[domain\n")
    with pytest.raises(SceneError, match="cannot read"):
        load_scene("/nonexistent/scene.toml")


@pytest.mark.parametrize("table,top,match", [
    ("[particles]\nper_cell_per_axis = 2\n", "particles = 2", "'particles' must be a table"),
    ("[numerics]\nflip = 0.99\n", "numerics = 1", "'numerics' must be a table"),
    ("[boundary]\nfriction = 0.5\ny_min = 0.0\ny_max = 0.0\n", "boundary = [1, 2]",
     "'boundary' must be a table"),
    ("", "wall = 3", r"'wall' must be an array of tables \(\[\[wall\]\]\)"),
    ("", "[wall]\naxis = \"x\"", r"'wall' must be an array of tables"),
])
def test_a_table_written_as_something_else_is_named(table, top, match):
    text = channel_column_toml(ColumnSpec())
    assert table in text
    body = text.replace(table, "")
    text = (top + "\n" + body) if not top.startswith("[") else (body + "\n" + top + "\n")
    with pytest.raises(SceneError, match=match):
        loads_scene(text)


@pytest.mark.parametrize("old,new,key", [
    ("per_cell_per_axis = 2", "per_cell_per_axis = inf", "particles.per_cell_per_axis"),
    ("size_m = [0.4, 0.04, 0.16]", 'size_m = "123"', "domain.size_m"),
])
def test_values_of_the_wrong_kind_are_named(old, new, key):
    text = channel_column_toml(ColumnSpec())
    with pytest.raises(SceneError, match=f"key '{key}' must be a"):
        loads_scene(text.replace(old, new))

"""Every benchmark in bench/ runs at a tiny size and prints the JSON lines it declares.

Each bench module declares its lines in KEYS ({line: (key, ...)}, bench/__init__.py): every
line it prints must carry exactly the keys of one of them, with finite numbers (null only
where a key ends in "?"), every declared line must appear, and the module's docstring must
name every key. No timing is asserted: the numbers of a smoke run mean nothing.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT_S = 300


def declared(module: str) -> tuple[dict[str, tuple[str, ...]], str]:
    """bench.{module}'s KEYS and docstring."""
    m = importlib.import_module(f"bench.{module}")
    assert isinstance(getattr(m, "KEYS", None), dict), f"bench.{module} declares no KEYS"
    return m.KEYS, m.__doc__ or ""


def finite(value, where: str, nullable: bool) -> None:
    """Every number in value (nested lists and dicts too) is finite; None only if nullable."""
    if value is None:
        assert nullable, f"{where} is null"
    elif isinstance(value, bool | str):
        pass
    elif isinstance(value, int | float):
        assert math.isfinite(value), f"{where} = {value}"
    elif isinstance(value, list):
        for k, v in enumerate(value):
            finite(v, f"{where}[{k}]", nullable)
    elif isinstance(value, dict):
        for k, v in value.items():
            finite(v, f"{where}.{k}", nullable)
    else:
        raise AssertionError(f"{where}: unexpected {type(value).__name__}")


def check_lines(module: str, lines: list[dict], expect: set[str] | None = None) -> None:
    """lines against bench.{module}.KEYS (module docstring); expect: the line names that must
    appear (default: all)."""
    keys, doc = declared(module)
    for name, names in keys.items():
        assert f'"{name.split()[0]}"' in doc, f"bench.{module}'s docstring never names {name!r}"
        missing = [k for k in names if f'"{k.rstrip("?")}"' not in doc]
        assert not missing, f"bench.{module}'s docstring never names {missing} ({name})"
    seen = set()
    for line in lines:
        shapes = {name: names for name, names in keys.items()
                  if name.split()[0] == line.get("bench")}
        assert shapes, f"bench.{module} printed an undeclared line: {line}"
        fits = [name for name, names in shapes.items()
                if set(line) == {"bench", *(k.rstrip("?") for k in names)}]
        assert fits, (f"bench.{module}: a line's keys {sorted(line)} are not those declared: "
                      f"{shapes}")
        seen.add(fits[0])
        for k in shapes[fits[0]]:
            finite(line[k.rstrip("?")], f"{line['bench']}.{k.rstrip('?')}", k.endswith("?"))
    absent = (set(keys) if expect is None else expect) - seen
    assert not absent, f"bench.{module} printed no {sorted(absent)} line"


def run_bench(module: str, *args) -> list[dict]:
    """`python -m bench.{module} ARGS` from the repository root, one numba thread per process
    unless the bench sets its own: its stdout must be JSON lines only, checked by
    check_lines; returns them."""
    proc = subprocess.run([sys.executable, "-m", f"bench.{module}", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert proc.returncode == 0, f"bench.{module} failed:\n{proc.stderr[-4000:]}"
    lines = [json.loads(text) for text in proc.stdout.splitlines() if text.strip()]
    assert lines, f"bench.{module} printed nothing"
    check_lines(module, lines)
    return lines


# A sweep config of few, small columns at the shipped checkpoint's resolution (particle
# spacing 0.016 m, frames 5 ms apart): its test split gives bench.oracle_loop,
# bench.oracle_calibration and bench.friction_limit a test_003 of 36 particles (288 in the
# MPM) and 0.06 s.
SMALL_SWEEP = """
seed = 1
duration_s = 0.06
output_interval_s = 0.0025
stride = 2
coarse_grain = 2
connectivity_radius_m = 0.029

[geometry]
particle_spacing_m = 0.016
cell_size_m = 0.032
domain_length_m = 0.32
domain_height_m = 0.16
length_m = [0.048, 0.064]
width_m = [0.064, 0.064]
aspect_ratio = [0.5, 2.0]
max_height_m = 0.128
friction_angle_deg = [25.0, 40.0]
particles = [10, 200]

[splits]
train = 0
valid = 0
test = 4
held_out_aspect_ratio = [[1.4, 1.7]]
held_out_friction_angle_deg = [[33.5, 36.5]]
"""


@pytest.fixture
def small_sweep(tmp_path) -> Path:
    path = tmp_path / "sweep.toml"
    path.write_text(SMALL_SWEEP)
    return path


def test_smoke_visibility():
    run_bench("visibility", "--scenes", "tiny", "--reps", 1)


def test_smoke_sim():
    run_bench("sim", "--steps-13k", 2, "--steps-100k", 0, "--steps-1m", 0, "--threads", 1,
              "--loaded-at-s", 0.001)


def test_smoke_gns():
    run_bench("gns", "--particles", 64, "--latent", 8, "--message-passing", 1)


def test_smoke_protocol():
    run_bench("protocol", "--sizes", 1000, "--port", free_port())


def test_smoke_render():
    run_bench("render", "--sizes", 1000, "--port", free_port())


def test_smoke_logread(tmp_path):
    run_bench("logread", "--repeat", 1, "--flush", "steps", "--dir", tmp_path)


def test_smoke_insitu():
    run_bench("insitu", "--sizes", "tiny", "--calls", 2)


def test_smoke_paper_table(tmp_path):
    """Two publishing runs, each with a fresh server on the same --out: the second logs to
    the --record path given although the first run's frame folder exists (issue 46)."""
    run_bench("paper_table", "--scenes", "tiny", "--steps", 40, "--repeats", 2, "--keep",
              tmp_path)


def test_smoke_sim_mpi():
    run_bench("sim_mpi", "--ranks", 1, 2, "--steps", 5, "--scene", "tiny", "--every", 1)


def test_smoke_render_mpi():
    run_bench("render_mpi", "--scene", "tiny", "--sizes", "64x48", "128x96", "--large", 0)


def test_smoke_complete(tmp_path):
    run_bench("complete", "--small", "--keep", tmp_path)


def test_smoke_surrogate(tmp_path):
    run_bench("surrogate", "gns/checkpoints/column_l64_m5.pt", "--scene", "tiny", "--no-mpm",
              "--threads", 1, "--out", tmp_path)


def test_smoke_friction_limit(small_sweep, tmp_path):
    run_bench("friction_limit", "--config", small_sweep, "--cases", "test_003_cfl0.3",
              "--threads", 1, "--out", tmp_path)


def test_smoke_oracle_calibration(small_sweep, tmp_path):
    run_bench("oracle_calibration", "--config", small_sweep, "--scene", "test_003", "--members",
              2, "--perturb", "both", "--widen", 0, "--runs", tmp_path / "runs", "--out",
              tmp_path)


def test_smoke_oracle_loop(small_sweep, tmp_path):
    """The closed loop only: the open loop's server and 2-rank sim, and the follower."""
    run_bench("oracle_loop", "--config", small_sweep, "--scenes", "test_003", "--frames", 12,
              "--loops", "closed", "--out", tmp_path)


def test_every_bench_module_has_a_smoke_test():
    modules = {p.stem for p in (ROOT / "bench").glob("[a-z]*.py")}
    assert modules == {name.removeprefix("test_smoke_") for name in globals()
                       if name.startswith("test_smoke_")}


def test_a_line_off_its_declaration_is_refused():
    """The checker itself: a missing key, an extra key, a NaN, an undeclared null and a
    declared line never printed each fail."""
    good = {"bench": "visibility", "scene": "tiny", "particles": 400, "view": "side",
            "kept": 0.5, "s": 0.001}
    check_lines("visibility", [good])
    for bad in ({k: v for k, v in good.items() if k != "kept"}, {**good, "extra": 1},
                {**good, "s": float("nan")}, {**good, "kept": None}):
        with pytest.raises(AssertionError):
            check_lines("visibility", [bad])
    with pytest.raises(AssertionError, match="printed no"):
        check_lines("render", [{"bench": "overlay", "width": 1, "height": 1, "compose_s": 0.1,
                                "apply_s": 0.1, "context_px": 1, "legend_px": 1}])

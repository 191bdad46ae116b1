"""The wheel installs and runs outside the source tree: built from a copy of the working
tree's files, installed (not editable) into a fresh venv, `minority demo` runs at its
smallest from a folder outside the repository and finds the shipped checkpoint, scene files
and colormap tables as package data.

The fresh venv borrows the project venv's dependencies instead of downloading them: a plain
path line in a .pth file puts the project venv's site-packages on its sys.path (a path line
runs nothing, so the editable install's import hook there stays off), and the wheel installs
with --no-deps. What the `mpich` wheel installs outside site-packages (libmpi in lib/, mpiexec in
bin/, where mpi4py and sim.launcher look for them) is linked in from the project venv."""

import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).parent.parent
SHIPPED = ("minority/gns/checkpoints/column_l64_m5.pt", "minority/gns/configs/column_sweep.toml",
           "minority/sim/scenes/tiny.toml", "minority/render_server/colormap_tables.npz",
           "minority/render_server/live_page.html")


def copy_working_tree(dst: Path) -> None:
    """The files git tracks or would track (symlinks as symlinks): what a clone plus the
    uncommitted work holds, without build/, *.egg-info or caches that a build in place would
    reuse (a stale build/lib ships deleted modules)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=ROOT, capture_output=True, check=True).stdout.decode()
    for name in filter(None, listed.split("\0")):
        src, out = ROOT / name, dst / name
        if not src.is_symlink() and not src.exists():  # deleted, not yet committed
            continue
        out.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            out.symlink_to(os.readlink(src))
        else:
            shutil.copy2(src, out)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    """(the wheel, pip's build output)."""
    tmp = tmp_path_factory.mktemp("wheel")
    copy_working_tree(tmp / "src")
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                            "--no-index", "-w", str(tmp / "dist"), str(tmp / "src")],
                           capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout + built.stderr
    (found,) = (tmp / "dist").glob("minority-*.whl")
    return found, built.stdout + built.stderr


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """A fresh venv with the wheel installed; returns its bin folder."""
    env = tmp_path_factory.mktemp("venv")
    venv.create(env, with_pip=False, symlinks=True)
    purelib = Path(sysconfig.get_path("purelib", vars={"base": str(env), "platbase": str(env)}))
    ours = {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}
    (purelib / "project_venv.pth").write_text("".join(f"{p}\n" for p in sorted(ours)))
    link_prefix_files("mpich", env)
    # --ignore-installed: the project venv's own `minority` (visible through the .pth) is
    # never uninstalled
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(env / "bin" / "python"),
                           "install", "--no-deps", "--no-index", "--ignore-installed", str(wheel[0])],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return env / "bin"


def link_prefix_files(dist_name: str, env: Path) -> None:
    """Links in `env` to the files that the project venv's `dist_name` installed outside its
    site-packages (its RECORD's ../../../ entries), as installing it there would place them;
    nothing when it is not installed (a cluster's own MPI is on PATH)."""
    try:
        files = distribution(dist_name).files or []
    except PackageNotFoundError:
        return
    prefix = Path(sys.prefix).resolve()
    for f in files:
        if f.parts[0] != "..":
            continue
        src = Path(distribution(dist_name).locate_file(f)).resolve()
        dst = env / src.relative_to(prefix)
        if not dst.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(src)


def elsewhere_env(bin_dir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PATH"] = os.pathsep.join([str(bin_dir), env.get("PATH", "")])
    return env


def test_the_wheel_holds_the_package_and_its_data_and_builds_without_warnings(wheel):
    path, printed = wheel
    names = zipfile.ZipFile(path).namelist()
    for name in SHIPPED:
        assert name in names, name
    assert {n.split("/")[0] for n in names if ".dist-info/" not in n} == {"minority"}
    assert not [n for n in names if "__pycache__" in n or n.endswith((".nbi", ".nbc"))]
    assert "absent from the `packages` configuration" not in printed


def test_the_installed_package_and_its_data_are_the_wheels(installed, tmp_path):
    """minority and its subpackages import from the new venv, not the source tree, and every
    default that names shipped data (the demo's and `minority oracle`'s checkpoint, the
    sweep config, the scenes, the colormap tables) is a file there."""
    code = """
import minority, minority.sim, minority.gns, minority.render_server, minority.protocol, minority.insitu
from minority.demo import CHECKPOINT
from minority.oracle_cli import DEFAULT_CHECKPOINT, DEFAULT_SWEEP
from minority.render_server.colormap import TABLES
from minority.sim.scene import builtin_scene_path
for m in (minority, minority.sim, minority.gns, minority.render_server, minority.protocol,
          minority.insitu):
    print(m.__file__)
for path in (CHECKPOINT, DEFAULT_CHECKPOINT, DEFAULT_SWEEP, TABLES, builtin_scene_path("tiny")):
    assert path.is_file(), path
    print(path)
"""
    out = subprocess.run([str(installed / "python"), "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120, env=elsewhere_env(installed))
    assert out.returncode == 0, out.stderr
    site = installed.parent.resolve()
    printed = out.stdout.split()
    assert len(printed) == 11
    for line in printed:
        assert Path(line).resolve().is_relative_to(site), line


def test_the_installed_demo_runs_from_outside_the_repository(installed, tmp_path):
    """The smallest demo (1 rank, 1,800 particles, 0.05 s, 6 frames, no follower): the
    oracle's checkpoint, the scene and the colormaps come from the installed package."""
    argv = [str(installed / "minority"), "demo", "-o", "demo", "--ranks", "1", "--duration", "0.05",
            "--cell-size", "0.032", "--frames", "6", "--no-follow"]
    out = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=1200,
                         env=elsewhere_env(installed))
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    for name in ("spec.json", "run.mcap", "score.json", "oracle/preview.png"):
        assert (tmp_path / "demo" / name).is_file(), name
    assert list((tmp_path / "demo" / "frames").rglob("*.png"))

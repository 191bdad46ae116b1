"""numba's cache=True misses edits to a callee's file; protocol.jitcache drops it, called by
the `minority` entry point (minority/cli.py main), never at import time."""

import os
import subprocess
import sys
import textwrap
from importlib.util import find_spec
from pathlib import Path

import pytest

from minority.cli import NUMBA_PACKAGES, main
from minority.protocol.jitcache import MARKER, drop_stale_numba_cache, numba_cache_dir, sources_digest

# what the entry point does before a command that runs kernels, then the command's import
ENTRY_POINT = textwrap.dedent("""
    import sys
    from pathlib import Path
    from minority.protocol.jitcache import drop_stale_numba_cache
    drop_stale_numba_cache(Path(sys.argv[1]) / "pkg")
    from pkg.caller import caller
    print(caller())
""")
CALLER = textwrap.dedent("""
    from numba import njit
    from pkg.callee import value

    @njit(cache=True)
    def caller():
        return value() + 0
""")
CALLEE = "from numba import njit\n\n@njit(cache=True, inline='always')\ndef value():\n    return {}\n"


def _env(root, cache_dir=None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    env["PYTHONPATH"] = os.pathsep.join([str(root), os.getcwd()])
    return env


def _run_caller(root, cache_dir=None) -> int:
    out = subprocess.run([sys.executable, "-c", ENTRY_POINT, str(root)], env=_env(root, cache_dir),
                         capture_output=True, text=True, timeout=120, check=True)
    return int(out.stdout.strip())


@pytest.mark.parametrize("user_cache", [False, True], ids=["pycache", "NUMBA_CACHE_DIR"])
def test_edit_of_a_callee_file_reaches_the_cached_caller(tmp_path, user_cache):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "caller.py").write_text(CALLER)
    (pkg / "callee.py").write_text(CALLEE.format(1))
    cache_dir = tmp_path / "numba-cache" if user_cache else None
    assert _run_caller(tmp_path, cache_dir) == 1
    where = cache_dir if user_cache else pkg / "__pycache__"
    assert list(where.rglob("caller.*.nbi"))  # the caller was cached there
    (pkg / "callee.py").write_text(CALLEE.format(2))  # caller.py untouched
    assert _run_caller(tmp_path, cache_dir) == 2  # without the guard numba returns the stale 1


def test_drop_keeps_a_matching_cache_and_drops_an_edited_one(tmp_path, monkeypatch):
    monkeypatch.setattr("numba.core.config.CACHE_DIR", "")
    (tmp_path / "a.py").write_text("x = 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    (cache / "a.f-1.py311.nbi").write_bytes(b"index")
    assert drop_stale_numba_cache(tmp_path)  # no marker yet: dropped
    assert not list(cache.glob("*.nbi"))
    assert (cache / MARKER).read_text() == sources_digest(tmp_path)
    (cache / "a.f-1.py311.nbi").write_bytes(b"index")
    assert not drop_stale_numba_cache(tmp_path)  # sources unchanged: kept
    assert list(cache.glob("*.nbi"))
    (tmp_path / "a.py").write_text("x = 2\n")
    assert drop_stale_numba_cache(tmp_path)  # edited: dropped
    assert not list(cache.glob("*.nbi"))


def test_drop_works_in_numba_cache_dir(tmp_path, monkeypatch):
    """With NUMBA_CACHE_DIR (as the systemd unit sets it) the cache is numba's directory for
    the package there, not __pycache__."""
    pkg, user = tmp_path / "pkg", tmp_path / "numba-cache"
    pkg.mkdir()
    (pkg / "a.py").write_text("x = 1\n")
    monkeypatch.setattr("numba.core.config.CACHE_DIR", str(user))
    cache = numba_cache_dir(pkg)
    assert cache.parent == user and cache.name.startswith("pkg_")
    cache.mkdir(parents=True)
    (cache / "a.f-1.py311.nbc").write_bytes(b"data")
    assert drop_stale_numba_cache(pkg)
    assert not list(cache.glob("*.nbc")) and (cache / MARKER).is_file()
    assert not (pkg / "__pycache__").exists()


@pytest.mark.parametrize("package", NUMBA_PACKAGES)
def test_the_cache_dir_is_the_one_numba_writes_for_the_package(package, tmp_path, monkeypatch):
    """Through the minority/X -> ../X symlinks the package's folder is minority/X: the cache
    folder under NUMBA_CACHE_DIR must be the one numba names from its modules' files."""
    from numba.core.caching import _CacheLocator

    monkeypatch.setattr("numba.core.config.CACHE_DIR", str(tmp_path))
    folder = Path(find_spec(package).submodule_search_locations[0])
    module = next(p for p in sorted(folder.glob("*.py")) if p.name != "__init__.py")
    numba_own = Path(tmp_path) / _CacheLocator.get_suitable_cache_subpath(
        find_spec(f"{package}.{module.stem}").origin)
    assert numba_cache_dir(folder) == numba_own


def test_importing_the_numba_packages_does_no_housekeeping(tmp_path):
    """No work at import time: the packages import without hashing or touching a cache."""
    cache = tmp_path / "numba-cache"
    code = f"import {', '.join(NUMBA_PACKAGES)}, minority.protocol"
    subprocess.run([sys.executable, "-c", code], env=_env(tmp_path, cache), check=True,
                   capture_output=True, timeout=120)
    assert not list(tmp_path.rglob(MARKER))


def test_the_entry_point_drops_stale_caches_before_a_command_that_runs_kernels(monkeypatch,
                                                                                capsys):
    called = []
    monkeypatch.setattr("minority.protocol.jitcache.drop_stale_numba_cache",
                        lambda folder: called.append(Path(folder)))
    assert main(["sim", "no_such_scene", "--quiet"]) == 2  # bad input, after the housekeeping
    assert called == [Path(find_spec(name).submodule_search_locations[0])
                      for name in NUMBA_PACKAGES]
    called.clear()
    assert main(["log", "check", "no_such.mcap"]) == 2  # runs no kernel: no housekeeping
    assert called == []


def test_the_housekeeping_does_not_import_numba_without_a_cache_dir(tmp_path):
    """Every command with kernels runs it first, the ranks' guards too: numba's default
    location is known without numba (about 60 MB of a process that never compiles)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    code = ("import sys\nfrom minority.cli import drop_stale_numba_caches\n"
            "drop_stale_numba_caches()\nprint('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=env, cwd=tmp_path)
    assert out.stdout.strip() == "False"

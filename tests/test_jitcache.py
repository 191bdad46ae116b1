"""numba's cache=True misses edits to a callee's file; protocol.jitcache drops it."""

import os
import subprocess
import sys
import textwrap

import pytest
from minority.protocol.jitcache import MARKER, drop_stale_numba_cache, numba_cache_dir, sources_digest

PACKAGE_INIT = textwrap.dedent("""
    from pathlib import Path
    from minority.protocol.jitcache import drop_stale_numba_cache
    drop_stale_numba_cache(Path(__file__).parent)
""")
CALLER = textwrap.dedent("""
    from numba import njit
    from pkg.callee import value

    @njit(cache=True)
    def caller():
        return value() + 0
""")
CALLEE = "from numba import njit\n\n@njit(cache=True, inline='always')\ndef value():\n    return {}\n"


def _run_caller(root, cache_dir=None) -> int:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    env["PYTHONPATH"] = os.pathsep.join([str(root), os.getcwd()])
    out = subprocess.run([sys.executable, "-c", "from pkg.caller import caller; print(caller())"],
                         env=env, capture_output=True, text=True, timeout=120, check=True)
    return int(out.stdout.strip())


@pytest.mark.parametrize("user_cache", [False, True], ids=["pycache", "NUMBA_CACHE_DIR"])
def test_edit_of_a_callee_file_reaches_the_cached_caller(tmp_path, user_cache):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(PACKAGE_INIT)
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

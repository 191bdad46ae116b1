"""Keep numba's on-disk cache (``cache=True``) in step with the sources.

numba keys a cached function on its own file's stamp and bytecode only: a jitted function
that calls (or inlines) one from another file keeps running the old callee after that
file is edited (e.g. a change to ``sim/plasticity.py`` does not reach the cached
``sim.kernels.g2p``). The `minority` entry point (minority/cli.py ``main``) calls
`drop_stale_numba_cache` for each numba package before a command that runs kernels, never at
import time: when the hash of the package's sources differs from the one recorded beside
its cache, the package's cache files are deleted and numba compiles afresh (any edit of
the package drops all of its kernels: about a minute of compiling at the next start). Code
that imports the kernels without the entry point (tests, bench/) calls it itself or runs
`make clean-numba` after an edit.
The cache is where numba puts it: ``__pycache__`` beside the sources, or numba's
directory for the package under ``NUMBA_CACHE_DIR`` when that is set (the systemd unit
sets it). numba treats a cache file removed under it as a miss, so concurrent processes
(MPI ranks) are safe. Not covered: a process still running the old code that compiles a
new signature after another process dropped the cache saves it under the new marker.
A read-only cache directory (a system install) is left alone.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

MARKER = "numba_sources.sha256"


def sources_digest(package_dir: Path) -> str:
    """SHA-256 over the names and bytes of the package's ``*.py`` files."""
    digest = hashlib.sha256()
    for path in sorted(package_dir.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def numba_cache_dir(package_dir: Path) -> Path:
    """Where numba caches the package's functions: ``NUMBA_CACHE_DIR``'s subdirectory for
    it (numba's own mapping) when set, else ``__pycache__`` beside the sources."""
    if ("numba" not in sys.modules and "NUMBA_CACHE_DIR" not in os.environ
            and not Path(".numba_config.yaml").exists()):
        return package_dir / "__pycache__"  # numba's default, known without importing it
    from numba.core import config
    if not config.CACHE_DIR:
        return package_dir / "__pycache__"
    from numba.core.caching import _CacheLocator
    # the path as numba sees the module's file (through minority/X -> ../X), not resolved
    init = os.path.abspath(package_dir / "__init__.py")
    return Path(config.CACHE_DIR) / _CacheLocator.get_suitable_cache_subpath(init)


def drop_stale_numba_cache(package_dir: str | os.PathLike) -> bool:
    """Delete the package's numba cache files (``*.nbi``, ``*.nbc``) if its sources changed
    since they were written; returns True when it dropped (or found nothing to keep)."""
    package_dir = Path(package_dir)
    try:
        cache = numba_cache_dir(package_dir)
        marker = cache / MARKER
        key = sources_digest(package_dir)
        if marker.is_file() and marker.read_text() == key:
            return False
        for path in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            path.unlink(missing_ok=True)
        cache.mkdir(parents=True, exist_ok=True)
        tmp = cache / f"{MARKER}.{os.getpid()}.tmp"
        tmp.write_text(key)
        os.replace(tmp, marker)
    except OSError:  # read-only: numba caches elsewhere (or not at all)
        return False
    return True

"""Keep numba's on-disk cache (``cache=True``) in step with the sources.

numba keys a cached function on its own file's stamp and bytecode only: a jitted function
that calls (or inlines) one from another file keeps running the old callee after that
file is edited (e.g. a change to ``sim/plasticity.py`` does not reach the cached
``sim.kernels.g2p``). Each numba package calls `drop_stale_numba_cache` from its
``__init__``: when the hash of the package's sources differs from the one recorded beside
its cache, the package's cache files are deleted and numba compiles afresh. numba treats
a cache file removed under it as a miss, so concurrent processes (MPI ranks) are safe.
With ``NUMBA_CACHE_DIR`` set, or a read-only install, the cache lives elsewhere and is
left alone (an installed package does not change in place).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

MARKER = "numba_sources.sha256"


def sources_digest(package_dir: Path) -> str:
    """SHA-256 over the names and bytes of the package's ``*.py`` files."""
    digest = hashlib.sha256()
    for path in sorted(package_dir.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def drop_stale_numba_cache(package_dir: str | os.PathLike) -> bool:
    """Delete ``package_dir/__pycache__/*.nbi|*.nbc`` if the sources changed since they were
    written; returns True when it deleted (or found nothing to keep)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return False
    package_dir = Path(package_dir)
    pycache = package_dir / "__pycache__"
    marker = pycache / MARKER
    try:
        key = sources_digest(package_dir)
        if marker.is_file() and marker.read_text() == key:
            return False
        for path in list(pycache.glob("*.nbi")) + list(pycache.glob("*.nbc")):
            path.unlink(missing_ok=True)
        pycache.mkdir(exist_ok=True)
        tmp = pycache / f"{MARKER}.{os.getpid()}.tmp"
        tmp.write_text(key)
        os.replace(tmp, marker)
    except OSError:  # read-only install: numba caches in its user-wide directory
        return False
    return True

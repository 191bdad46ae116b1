"""Benchmarks: run as modules from the repository root, e.g. `python -m bench.protocol`."""

from minority.cli import drop_stale_numba_caches

drop_stale_numba_caches()  # as the `minority` command does: a kernel edited since is recompiled

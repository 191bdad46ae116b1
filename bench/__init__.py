"""Benchmarks: run as modules from the repository root, e.g. `python -m bench.protocol`.

Each module prints JSON lines and declares them in `KEYS`: {line: (key, ...)}, where a line
is named by its "bench" value (a second word tells apart two kinds of line with the same
value) and a key ending in "?" may be null. Its docstring names every key, quoted;
tests/test_bench_smoke.py runs every module at a tiny size and checks both.
"""

from minority.cli import drop_stale_numba_caches

drop_stale_numba_caches()  # as the `minority` command does: a kernel edited since is recompiled

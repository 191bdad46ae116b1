"""Graph network simulator: dataset, model, training, rollout, the oracle."""

from pathlib import Path

from minority.protocol.jitcache import drop_stale_numba_cache

drop_stale_numba_cache(Path(__file__).parent)  # numba does not track cross-file changes

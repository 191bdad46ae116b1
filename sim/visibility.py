"""Occlusion culling moved to minority.insitu.visibility; this name stays for the callers
that still import it from here (tests/test_projection.py)."""

from minority.insitu.visibility import visible_mask  # noqa: F401

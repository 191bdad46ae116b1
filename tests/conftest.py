"""Shared fixtures: loopback zenoh sessions (127.0.0.1, multicast off) and sample messages."""

from __future__ import annotations

import errno
import os
import shutil
import socket
import subprocess
import tempfile
import zlib

import numpy as np
import pytest

from minority.protocol import Chunk, Event, EventKind, Frame, Spec, Stats, Timing
from minority.protocol.auth import CREDENTIALS_ENV
from minority.protocol.session import NetworkOptions, Role, open_session


def pytest_configure(config) -> None:
    """Servers' credentials (protocol.auth) go to a directory of this test session, never the
    user's own (subprocesses inherit it); numba caches of edited kernels are dropped first, as
    the `minority` command does."""
    from minority.cli import drop_stale_numba_caches

    drop_stale_numba_caches()
    config._minority_credentials = tempfile.mkdtemp(prefix="minority-credentials-")
    os.environ[CREDENTIALS_ENV] = config._minority_credentials


def pytest_unconfigure(config) -> None:
    shutil.rmtree(getattr(config, "_minority_credentials", ""), ignore_errors=True)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def server(endpoint):
    session = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    yield session
    session.close()


@pytest.fixture
def render_server_of(server, tmp_path):
    """A function spec -> a RenderServer on the `server` session, frames under
    tmp_path/frames and its log tmp_path/run.mcap, 30 s step timeout; closed at teardown."""
    from minority.render_server.daemon import RenderServer, ServerOptions

    started = []

    def start(spec):
        d = RenderServer(server, ServerOptions(spec, tmp_path / "frames", tmp_path / "run.mcap",
                                               timeout_s=30.0))
        started.append(d)
        return d

    yield start
    for d in started:
        d.close()


@pytest.fixture
def client_factory(server, endpoint):
    sessions = []

    def make():
        s = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5.0), Role.CLIENT)
        sessions.append(s)
        return s

    yield make
    for s in sessions:
        s.close()


def make_chunk(n: int = 100, step: int = 20, rank: int = 0, ranks: int = 2, seed: int = 0,
               run: str = "test-run") -> Chunk:
    rng = np.random.default_rng(seed)
    return Chunk(run=run, step=step, time_s=step * 1e-4, rank=rank, ranks=ranks, spacing_m=0.005,
                 bounds_m=((0.0, 0.0, 0.0), (1.0, 0.5, 0.5)),
                 fields={"positions": rng.random((n, 3), dtype=np.float32),
                         "displacement": rng.random((n, 3), dtype=np.float32),
                         "velocity_magnitude": rng.random(n, dtype=np.float32),
                         "material": rng.integers(0, 3, n).astype(np.uint8)})


def make_png(width: int = 4, height: int = 3) -> bytes:
    """A tiny valid RGB PNG, built by hand (deterministic bytes)."""
    def block(tag: bytes, data: bytes) -> bytes:
        return (len(data).to_bytes(4, "big") + tag + data
                + zlib.crc32(tag + data).to_bytes(4, "big"))
    raw = b"".join(b"\x00" + bytes(range(y, y + 3 * width)) for y in range(height))
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + block(b"IHDR", ihdr) + block(b"IDAT", zlib.compress(raw, 9))
            + block(b"IEND", b""))


def make_spec(run: str = "test-run") -> Spec:
    return Spec.from_dict({
        "version": 1, "run": run,
        "views": [{"name": "side", "camera": {"position": [0.5, -2.0, 0.2],
                                              "focal_point": [0.5, 0.25, 0.1],
                                              "view_up": [0, 0, 1], "view_angle_deg": 30},
                   "width": 640, "height": 480, "range": [0.0, 0.38],
                   "t_start_s": 0.0, "t_end_s": 0.15, "every_steps": 20},
                  {"name": "top", "camera": {"position": [0.5, 0.25, 3.0],
                                             "focal_point": [0.5, 0.25, 0.0],
                                             "view_up": [0, 1, 0], "parallel_projection": True,
                                             "parallel_scale_m": 0.4},
                   "field": "velocity_magnitude", "range": [0.0, 2.0], "t_start_s": 0.15}]})


def sample_messages() -> list:
    return [make_chunk(), make_spec(),
            Frame("test-run", "side", 40, 0.004, 4, 3, make_png()),
            Timing("test-run", 40, "side", 0.004, 0.01, 0.002, 0.03, 4096, 100, 2, 2, False),
            Event("test-run", EventKind.RANK_DONE, 1, "rank 1 done", {"dropped": 0}),
            Stats("test-run", 1, 40, 0.004, 100, 12.5, 0.75, 0.02, True,
                  [0] * 40 + [60] + [0] * 11, [0] * 30 + [40] + [0] * 21)]


def fail_call(real, at: int, exc: Exception):
    """Wrap `real` so that its `at`-th call (1-based) raises `exc` (e.g. a full disk);
    returns the wrapper and the list of call arguments it records."""
    calls = []

    def wrapper(*args, **kwargs):
        calls.append(args)
        if len(calls) == at:
            raise exc
        return real(*args, **kwargs)

    return wrapper, calls


# two small views of sim/scenes/tiny.toml's run (tests/test_serve_mpi.py, tests/test_slurm.py)
TINY_SPEC = {
    "version": 2, "run": "tiny",
    "regions": [{"name": "front", "lo_m": [0.05, -1.0, -1.0], "hi_m": [1.0, 1.0, 1.0]}],
    "views": [
        {"name": "side", "camera": {"position": [0.2, -1.0, 0.08],
                                    "focal_point": [0.2, 0.02, 0.08]},
         "width": 64, "height": 48, "field": "displacement", "range": [0.0, 0.1],
         "schedule": [{"every_steps": 20, "regions": ["front"]}]},
        {"name": "top", "camera": {"position": [0.2, 0.02, 1.0], "focal_point": [0.2, 0.02, 0.0],
                                   "view_up": [0, 1, 0], "parallel_projection": True,
                                   "parallel_scale_m": 0.1},
         "width": 64, "height": 48, "field": "displacement", "range": [0.0, 0.1],
         "decimate": 2, "schedule": [{"every_steps": 40}]}]}


DISK_BYTES = 2 << 20  # the `disk` fixture's tmpfs
PAGE_BYTES = 4096


@pytest.fixture
def disk(tmp_path):
    """A 2 MiB tmpfs mounted on a fresh directory (needs root: skipped otherwise)."""
    where = tmp_path / "disk"
    where.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK_BYTES}", "tmpfs",
                               str(where)], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"cannot mount a tmpfs to fill: {exc}")
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs to fill (root needed): {done.stderr.strip()}")
    try:
        yield where
    finally:
        # -l: a test that failed may still hold a file there open
        subprocess.run(["umount", "-l", str(where)], check=True, timeout=30)


def fill(where, leave: int = 0) -> None:
    """Write a filler file until the disk is full, or until about `leave` bytes are free."""
    fd = os.open(where / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        block = b"\0" * (64 << 10)
        while os.statvfs(where).f_bavail * os.statvfs(where).f_frsize > leave + len(block):
            os.write(fd, block)
        if leave:
            return
        while True:
            try:
                os.write(fd, block[:PAGE_BYTES])
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
                return
    finally:
        os.close(fd)

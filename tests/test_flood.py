"""Idle connections cannot shut clients out: any local process can open TCP connections to
the server's port and send nothing; zenoh holds each until its handshake times out. The
embedded server bounds how many it holds and for how long (protocol.session ACCEPT_*), so a
client still gets in. Loopback only; waits are bounded and wait on events (a session
opened, a socket closed)."""

import select
import socket
import time

import pytest

from minority.protocol.session import (
    ACCEPT_PENDING,
    ACCEPT_TIMEOUT_MS,
    NetworkOptions,
    Role,
    open_session,
)

IDLE = 150  # the flood of the report: 150 idle connections to the endpoint
WAIT_S = 5.0  # the client's --wait: zenoh's own 10 s accept timeout would exceed it


@pytest.fixture
def idle_sockets(server, endpoint):
    """IDLE plain TCP connections to the server (connected, nothing sent), closed at teardown."""
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    socks = [socket.create_connection((host, int(port)), timeout=5) for _ in range(IDLE)]
    yield socks
    for s in socks:
        s.close()


def closed_within(socks: list[socket.socket], timeout_s: float) -> int:
    """How many of `socks` the peer closed (EOF or reset) within `timeout_s`."""
    poller = select.poll()
    by_fd = {s.fileno(): s for s in socks}
    for fd in by_fd:
        poller.register(fd, select.POLLIN | select.POLLHUP | select.POLLERR)
    closed, deadline = set(), time.monotonic() + timeout_s
    while len(closed) < len(socks) and (left := deadline - time.monotonic()) > 0:
        for fd, _ in poller.poll(int(left * 1000) + 1):
            try:
                data = by_fd[fd].recv(1, socket.MSG_DONTWAIT)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if data == b"":
                closed.add(fd)
                poller.unregister(fd)
    return len(closed)


def test_idle_connections_do_not_lock_a_client_out(idle_sockets, endpoint):
    assert IDLE < ACCEPT_PENDING  # held, not refused: they take no client's place
    client = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=WAIT_S),
                          Role.CLIENT)
    client.close()


def test_the_server_closes_idle_connections_after_its_accept_timeout(idle_sockets):
    """Each unauthenticated connection lives a bounded time (with room for the accepts of a
    loaded machine), so a flood larger than ACCEPT_PENDING delays a client a bounded time."""
    assert closed_within(idle_sockets, 5 * ACCEPT_TIMEOUT_MS / 1000) == IDLE

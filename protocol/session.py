"""The one zenoh session factory every networked command uses, its shared CLI flags,
and the explicit QoS of each message stream.

Embedded default (one machine, no router to install): the render server is a peer that
listens on tcp/127.0.0.1:7447; ranks, recorders and replays are clients that connect to
it. Multicast scouting is off. The server requires a password that it keeps in a file only
its user can read, and local clients send it (protocol.auth); a client connects to a local
endpoint only when that file exists and the listening socket is its user's, so another
user's process on the port receives nothing. Connections that have not finished zenoh's
handshake are bounded in number and time (ACCEPT_PENDING, ACCEPT_TIMEOUT_MS), so idle
connections from anyone who can reach the port cannot lock clients out for long. Shared
memory is on, with an implicit-SHM pool large enough for a 1M-particle chunk, so large puts
between processes on one host skip the TCP copy.
zenoh writes the whole pool when a session first puts through it (about 3 ms of CPU per
MiB here), so a sender that knows its largest message sizes the pool with `shm_pool_for`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import zenoh

from minority.protocol.auth import (
    Credentials,
    NoCredentialsError,
    client_credentials,
    credentials_dir,
    forget_server_credentials,
    read_credentials,
    server_credentials,
)
from minority.protocol.wire import stamp_sent

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
# 1M particles x (positions [n,3] f4 + 4 scalar f4 fields) = 28 MB; room for two in flight.
SHM_POOL_BYTES = 64 * 1024 * 1024
SHM_POOL_MIN_BYTES = 8 * 1024 * 1024
SHM_POOL_MAX_BYTES = 512 * 1024 * 1024
SHM_THRESHOLD_BYTES = 3072  # messages above this size go through shared memory on one host
# Transmission queue: batches per priority (zenoh default 2). Data streams get deeper queues so
# a burst of chunks from one step does not stall the sender; bounded, so memory stays bounded.
TX_QUEUE_BATCHES = {"control": 2, "real_time": 2, "interactive_high": 4, "interactive_low": 4,
                    "data_high": 8, "data": 16, "data_low": 8, "background": 2}
DROP_WAIT_US = 1000  # with DROP congestion control, wait this long for room before dropping
# A listener's connections that have not finished zenoh's handshake (with the password):
# zenoh closes one after ACCEPT_TIMEOUT_MS, and closes a new one at once while
# ACCEPT_PENDING are open. With zenoh's defaults (10 s, 100), 150 idle sockets from any local
# process lock clients out for 10 s (a client with --wait 30 got in after 10.1 s); with these
# they take no client's place (tests/test_flood.py). A client's handshake on one host takes
# milliseconds. 512 stays within the common 1024 open-file limit with room for the server's
# own files. A flood beyond 512 delays a retrying client about ACCEPT_TIMEOUT_MS plus the time
# the server takes to accept them (600 idle: in 2.3-4.2 s here); a flood that reconnects as
# fast as it is closed is not bounded so.
ACCEPT_TIMEOUT_MS = 2000
ACCEPT_PENDING = 512


class Role(StrEnum):
    SERVER = "server"  # a listening peer that routes for the clients
    CLIENT = "client"  # connects to a server (ranks, recorder, replay)


@dataclass
class NetworkOptions:
    """--connect / --listen / --config, shared by every networked command."""

    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config: Path | None = None
    connect_timeout_s: float = 0.0  # clients: keep retrying for this long at start (0 = once)
    shm_pool_bytes: int = SHM_POOL_BYTES  # implicit shared-memory pool (embedded config only)
    auth: bool = True  # embedded default: user/password authentication (protocol.auth)
    credentials_file: Path | None = None  # --credentials: this file instead of the local one
    credentials: Credentials | None = None  # resolved by with_credentials (make_config uses it)


def shm_pool_for(message_bytes: int) -> int:
    """A pool for two messages of at most `message_bytes` in flight, within
    [SHM_POOL_MIN_BYTES, SHM_POOL_MAX_BYTES]; a message that does not fit goes over TCP."""
    return int(min(max(2 * message_bytes, SHM_POOL_MIN_BYTES), SHM_POOL_MAX_BYTES))


def add_network_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("network (zenoh)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to connect to, repeatable (clients default to {DEFAULT_ENDPOINT})")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on, repeatable (the server defaults to {DEFAULT_ENDPOINT})")
    g.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="zenoh JSON5 config file; it replaces the embedded default, and "
                        "--connect/--listen still override its endpoints")
    g.add_argument("--credentials", type=Path, default=None, metavar="FILE",
                   help="a 'user:password' file (mode 600): a listening peer requires it, a "
                        "client sends it (default: on one host, the server makes one per "
                        f"endpoint in {credentials_dir()} and local clients read it)")
    g.add_argument("--no-auth", action="store_true",
                   help="no password: a listening peer lets any peer connect, and a client "
                        "connects to a local endpoint that has no password file (whoever "
                        "listens there gets what it sends)")


def options_from_args(args: argparse.Namespace) -> NetworkOptions:
    return NetworkOptions(connect=list(args.connect), listen=list(args.listen), config=args.config,
                          auth=not args.no_auth, credentials_file=args.credentials)


def with_credentials(opts: NetworkOptions, role: Role) -> NetworkOptions:
    """Resolve the credentials of the embedded default (protocol.auth): a server makes or
    reuses its endpoints' password (or, with auth off, removes their files); a client reads
    the file of the local endpoints it connects to, and with auth on refuses one it cannot
    authenticate (NoCredentialsError, ForeignServerError). A --config file decides for
    itself."""
    if opts.credentials is not None:
        return opts
    if opts.credentials_file is not None:
        return dataclasses.replace(opts, credentials=read_credentials(opts.credentials_file))
    if opts.config is not None:
        return opts
    if role is Role.SERVER:
        listen = opts.listen or [DEFAULT_ENDPOINT]
        if not opts.auth:
            forget_server_credentials(listen)
            return opts
        return dataclasses.replace(opts, credentials=server_credentials(listen))
    return dataclasses.replace(opts, credentials=client_credentials(
        opts.connect or [DEFAULT_ENDPOINT], required=opts.auth))


def _put(cfg: zenoh.Config, key: str, value) -> None:
    cfg.insert_json5(key, json.dumps(value))


def make_config(opts: NetworkOptions, role: Role) -> zenoh.Config:
    """The zenoh config for `role`: embedded default or the --config file, then the flags."""
    if opts.config is not None:
        cfg = zenoh.Config.from_file(str(opts.config))
    else:
        cfg = zenoh.Config()
        _put(cfg, "mode", "peer" if role is Role.SERVER else "client")
        _put(cfg, "scouting/multicast/enabled", False)
        _put(cfg, "scouting/gossip/enabled", False)
        _put(cfg, "transport/shared_memory/enabled", True)
        _put(cfg, "transport/shared_memory/transport_optimization",
             {"enabled": True, "pool_size": int(opts.shm_pool_bytes),
              "message_size_threshold": SHM_THRESHOLD_BYTES})
        _put(cfg, "transport/link/tx/queue/size", TX_QUEUE_BATCHES)
        _put(cfg, "transport/link/tx/queue/congestion_control/drop/wait_before_drop", DROP_WAIT_US)
        if role is Role.SERVER:
            _put(cfg, "transport/unicast/accept_timeout", ACCEPT_TIMEOUT_MS)
            _put(cfg, "transport/unicast/accept_pending", ACCEPT_PENDING)
            _put(cfg, "listen/endpoints", opts.listen or [DEFAULT_ENDPOINT])
        else:
            _put(cfg, "listen/endpoints", opts.listen)
    if opts.listen:
        _put(cfg, "listen/endpoints", opts.listen)
    if opts.connect or (opts.config is None and role is Role.CLIENT):
        _put(cfg, "connect/endpoints", opts.connect or [DEFAULT_ENDPOINT])
    if opts.credentials is not None:  # see with_credentials
        c = opts.credentials
        if role is Role.SERVER:
            _put(cfg, "transport/auth/usrpwd/dictionary_file", str(c.path))
        else:
            _put(cfg, "transport/auth/usrpwd/user", c.user)
            _put(cfg, "transport/auth/usrpwd/password", c.password)
    if role is Role.CLIENT and opts.connect_timeout_s > 0:
        _put(cfg, "connect/timeout_ms", {"client": int(opts.connect_timeout_s * 1000)})
        _put(cfg, "connect/retry", {"period_init_ms": 50, "period_max_ms": 500,
                                    "period_increase_factor": 2})
    return cfg


CONNECT_ATTEMPT_S = 1.0  # a client's connect timeout is tried in attempts this long
RETRY_WAIT_S = 0.05  # between attempts that failed at once (e.g. refused without credentials)


def open_session(opts: NetworkOptions | None = None, role: Role = Role.CLIENT,
                 configure: Callable[[zenoh.Config], None] | None = None) -> zenoh.Session:
    """Open a zenoh session (`configure` may edit the config first). A client keeps trying
    for opts.connect_timeout_s, in attempts that each read the server's credentials anew (a
    server started at the same moment writes them first; a client started before it waits
    for the file). A client with no server to connect to, or refused by it (wrong
    credentials), raises zenoh.ZError; one that cannot authenticate a local endpoint (no
    password file by the deadline: NoCredentialsError; another user's listener:
    ForeignServerError) or has an unusable credentials file raises CredentialsError, before
    any session is opened."""
    opts = opts or NetworkOptions()
    deadline = time.monotonic() + opts.connect_timeout_s
    while True:
        left = deadline - time.monotonic()
        attempt = opts
        if role is Role.CLIENT and opts.connect_timeout_s > 0:
            attempt = dataclasses.replace(opts, connect_timeout_s=max(min(left, CONNECT_ATTEMPT_S),
                                                                      0.01))
        try:
            resolved = with_credentials(attempt, role)
        except NoCredentialsError as exc:
            if role is not Role.CLIENT or time.monotonic() >= deadline:
                if opts.connect_timeout_s > 0:
                    raise NoCredentialsError(f"{exc} (waited {opts.connect_timeout_s:g} s for "
                                             f"the file)") from None
                raise
            threading.Event().wait(RETRY_WAIT_S)
            continue
        cfg = make_config(resolved, role)
        if configure is not None:
            configure(cfg)
        try:
            return zenoh.open(cfg)
        except zenoh.ZError:
            if role is not Role.CLIENT or time.monotonic() >= deadline:
                raise
        threading.Event().wait(RETRY_WAIT_S)


@dataclass(frozen=True)
class QoS:
    """Explicit publisher settings for one message stream."""

    congestion: zenoh.CongestionControl
    priority: zenoh.Priority
    express: bool = False


# Chunks never block the simulation: a full queue drops (counted by the sender).
CHUNK_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA)
# Frames are for watching; the newest matters, old ones may drop.
FRAME_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_LOW)
# Spec, timing and lifecycle events are small and must arrive.
CONTROL_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_HIGH, express=True)
# Tests and replays that need every chunk delivered.
LOSSLESS_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA)


class Publisher:
    """A zenoh publisher with explicit QoS that stamps the sent time into each payload."""

    def __init__(self, session: zenoh.Session, key: str, qos: QoS):
        self.key = key
        self._pub = session.declare_publisher(key, congestion_control=qos.congestion,
                                              priority=qos.priority, express=qos.express)

    def put(self, payload: bytearray) -> None:
        stamp_sent(payload)
        self._pub.put(payload)

    @property
    def matched(self) -> bool:
        return bool(self._pub.matching_status.matching)

    def close(self) -> None:
        self._pub.undeclare()


def put(session: zenoh.Session, key: str, payload: bytearray, qos: QoS) -> None:
    """One-off publish with explicit QoS (for keys that vary, e.g. chunk/{step}/{rank})."""
    stamp_sent(payload)
    session.put(key, payload, congestion_control=qos.congestion, priority=qos.priority,
                express=qos.express)


@dataclass(frozen=True)
class Received:
    key: str
    payload: bytes
    recv_ns: int  # time.time_ns() at arrival


class Inbox:
    """A bounded queue of the samples received on one key expression (or several); when full
    (`capacity` messages or `max_bytes` of payload), new samples are dropped and counted.

    The zenoh callback only copies the payload and enqueues, so a slow consumer never
    stalls zenoh's threads and memory stays bounded.
    """

    def __init__(self, session: zenoh.Session, key: str | list[str], capacity: int = 256,
                 max_bytes: int | None = None):
        self.dropped = 0
        self.received = 0
        self.max_bytes = max_bytes
        self._queued_bytes = 0
        self._queue: queue.Queue[Received] = queue.Queue(maxsize=capacity)
        self._lock = threading.Lock()
        self._subs = [session.declare_subscriber(k, self._on_sample)
                      for k in ([key] if isinstance(key, str) else key)]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        with self._lock:
            self.received += 1
            if self.max_bytes is not None and self._queued_bytes + size > self.max_bytes:
                self.dropped += 1
                return
        item = Received(str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())
        with self._lock:
            try:
                self._queue.put_nowait(item)
                self._queued_bytes += size
            except queue.Full:
                self.dropped += 1

    def get(self, timeout: float | None = None) -> Received | None:
        """The next sample, or None after `timeout` seconds."""
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        with self._lock:
            self._queued_bytes -= len(item.payload)
        return item

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()

"""One-host authentication that costs the user nothing: zenoh's user/password transport
authentication with a password the server makes and keeps in a file only its user can read.

A server (the listening peer of the embedded default) creates, or reuses, a random password
per local endpoint it listens on, in `credentials_dir()/{protocol}-{port}.usrpwd` (mode 600
in a mode 700 directory; one line `minority:PASSWORD`, the format of zenoh's
`transport/auth/usrpwd/dictionary_file`). Clients of the same user that connect to a local
endpoint (an address of this host: loopback, a wildcard, one of its interfaces) read the file for
that endpoint and authenticate. A peer without the password is refused when it opens its
link, before it can subscribe, put, query or declare a liveliness token, so it can neither
forge messages into a run nor read one. The password is kept across server restarts, so
ranks whose server restarts reconnect.

The other direction, a client that must not talk to an impostor: zenoh's user/password
handshake proves the client to the server, never the server to the client; any process may
listen on a free local port and accept a client that offers a password. So a client of the
embedded default connects to a local endpoint only when (1) the endpoint's password file
exists (the server of this user wrote it; with none, `client_credentials` raises
NoCredentialsError, whose message names the endpoint, the file and the fixes) and (2) on
Linux, the socket listening there belongs to this user (/proc/net/tcp; another user's
raises ForeignServerError). The second closes the case of a stale file: this user's server
stopped and another user took its port. `--no-auth` on a client waives both; `--credentials
FILE` is a secret shared on purpose (perhaps with another user's server) and waives (2).

Why the transport and not a token in each message's header: every subscriber of a run sees
its headers, so a header token is known to any peer that can connect at all; refusing the
link to a peer without the password closes both reading and forging and adds nothing to a
message. Across hosts, use certificates and per-run access control (deploy/README.md), or
pass the same file to both sides with `--credentials FILE`.
"""

from __future__ import annotations

import functools
import ipaddress
import os
import re
import secrets
import socket
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

AUTH_USER = "minority"
CREDENTIALS_ENV = "MINORITY_CREDENTIALS_DIR"  # overrides credentials_dir() (tests, services)
_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z]+)/(?P<host>\[[^\]]*\]|[^:/]+):(?P<port>\d{1,5})")
TCP_PROTOCOLS = {"tcp", "tls", "ws"}  # links over TCP: their listeners are in /proc/net/tcp*
FIXES = ("start `minority serve` first (a client waits for it with --wait S), or pass --no-auth "
         "to the server and its clients, or --credentials FILE to both")


class CredentialsError(OSError):
    """A credentials file that cannot be used (unsafe permissions, another owner, garbled)."""


class NoCredentialsError(CredentialsError):
    """A local endpoint without its password file: the peer there cannot be authenticated
    (no server of this user has started there), so a client sends nothing to it."""


class ForeignServerError(CredentialsError):
    """A local endpoint whose listening socket belongs to another user."""


@dataclass(frozen=True)
class Credentials:
    path: Path  # the file: one line "user:password", mode 600
    user: str
    password: str


def credentials_dir() -> Path:
    env = os.environ.get(CREDENTIALS_ENV)
    if env:
        return Path(env)
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    return (Path(runtime) if runtime else Path.home() / ".cache") / "minority"


@functools.lru_cache(maxsize=64)
def host_addresses(host: str) -> tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, ...]:
    """The addresses of this host that `host` (an endpoint's host: an IP, `[v6]` or a name)
    stands for, as a connection to it reaches them (a wildcard reaches loopback); () for a
    host that is not this one or does not resolve."""
    host = host.strip("[]").split("%")[0]
    try:
        ips = [ipaddress.ip_address(host)]
    except ValueError:
        try:
            ips = [ipaddress.ip_address(info[4][0].split("%")[0])
                   for info in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)]
        except (OSError, UnicodeError, ValueError):
            return ()
    local = []
    for ip in ips:
        if ip.version == 6 and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        if ip.is_unspecified:
            ip = ipaddress.ip_address("127.0.0.1" if ip.version == 4 else "::1")
        if ip.is_loopback or _assigned_here(ip):
            local.append(ip)
    return tuple(dict.fromkeys(local))


def _assigned_here(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Whether `ip` is an address of one of this host's interfaces (binding to it works)."""
    family = socket.AF_INET if ip.version == 4 else socket.AF_INET6
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.bind((str(ip), 0))
        return True
    except OSError:
        return False


def credentials_path(endpoint: str) -> Path | None:
    """The file of a local endpoint (`tcp/127.0.0.1:7447` -> `tcp-7447.usrpwd`; local: an
    address of this host); None for an endpoint on another host (its password is not ours
    to send) or one that is not host:port (a unix socket: its directory guards it)."""
    m = _ENDPOINT_RE.match(endpoint)
    if m is None or not host_addresses(m["host"]):
        return None
    return credentials_dir() / f"{m['proto']}-{int(m['port'])}.usrpwd"


def read_credentials(path: Path) -> Credentials:
    """Read a credentials file; refuse one that others may read or that another user owns."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise CredentialsError(f"{path}: no such credentials file") from None
    if st.st_mode & 0o077:
        raise CredentialsError(f"{path}: credentials readable by others (mode "
                               f"{stat.S_IMODE(st.st_mode):o}); chmod 600 it")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise CredentialsError(f"{path}: credentials owned by another user")
    line = path.read_text(encoding="utf-8", errors="replace").strip()
    user, sep, password = line.partition(":")
    if not sep or not user or not password or "\n" in line:
        raise CredentialsError(f"{path}: expected one line 'user:password'")
    return Credentials(path, user, password)


def _write_private(path: Path, text: str) -> None:
    """Write `text` to `path` with mode 600, atomically (a reader never sees half a file)."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(path.parent, 0o700)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


def server_credentials(listen: list[str]) -> Credentials | None:
    """The password of a server listening on `listen`: reused from the first local
    endpoint's file, else new; written for every local endpoint. None: no local endpoint."""
    paths = [p for p in map(credentials_path, listen) if p is not None]
    if not paths:
        return None
    creds = None
    for path in paths:
        if path.exists():
            creds = read_credentials(path)
            break
    if creds is None:
        creds = Credentials(paths[0], AUTH_USER, secrets.token_urlsafe(24))
    for path in paths:
        if not path.exists() or read_credentials(path) != Credentials(path, creds.user,
                                                                      creds.password):
            _write_private(path, f"{creds.user}:{creds.password}\n")
    return Credentials(paths[0], creds.user, creds.password)


def forget_server_credentials(listen: list[str]) -> None:
    """A server without authentication: remove its endpoints' files, so clients do not offer
    a password it would refuse."""
    for path in filter(None, map(credentials_path, listen)):
        path.unlink(missing_ok=True)


def client_credentials(connect: list[str], required: bool = True) -> Credentials | None:
    """The credentials a client sends to the endpoints in `connect`: those of the first local
    endpoint's file; None when no endpoint is local.

    required (the default; --no-auth waives it): every local endpoint must be authenticated
    before anything is sent to it, since zenoh may connect to any of them: its file must exist
    (else NoCredentialsError) and, where the system says (Linux), the socket listening there
    must be this user's (else ForeignServerError). Not required: the first file found, or
    None (the server then needs no password, or refuses the link)."""
    found = None
    for endpoint in connect:
        path = credentials_path(endpoint)
        if path is None:
            continue
        if not path.exists():
            if required:
                raise NoCredentialsError(
                    f"{endpoint}: no password file {path}, so the server there cannot be "
                    f"authenticated and nothing is sent to it (another user's process may "
                    f"be listening): {FIXES}")
            continue
        creds = read_credentials(path)
        if required:
            check_listener(endpoint, path)
        found = found or creds
    return found


def check_listener(endpoint: str, path: Path) -> None:
    """Raise ForeignServerError when the TCP socket listening at local `endpoint` belongs to
    another user (its password file `path` is then stale: this user's server is gone)."""
    others = listener_uids(endpoint) - {os.getuid()}
    if others:
        raise ForeignServerError(
            f"{endpoint}: the socket listening there belongs to another user (uid "
            f"{', '.join(map(str, sorted(others)))}), not to the server that wrote {path}; "
            f"nothing is sent to it: stop that process, or use another port")


def listener_uids(endpoint: str) -> set[int]:
    """The owners (uids) of the TCP sockets of this host listening where a connection to
    `endpoint` lands: its address, or a wildcard, on its port. Empty when none listens, when
    the endpoint is not a local TCP one, or when the system does not say (no /proc/net)."""
    m = _ENDPOINT_RE.match(endpoint)
    if m is None or m["proto"] not in TCP_PROTOCOLS:
        return set()
    port, targets = int(m["port"]), set(host_addresses(m["host"]))
    uids = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table, encoding="ascii") as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            cols = row.split()
            if len(cols) < 8 or cols[3] != "0A":  # 0A: TCP_LISTEN
                continue
            addr_hex, _, port_hex = cols[1].partition(":")
            if int(port_hex, 16) != port:
                continue
            ip = _proc_address(addr_hex)
            if ip.version == 6 and ip.ipv4_mapped is not None:
                ip = ip.ipv4_mapped
            if ip.is_unspecified or ip in targets:
                uids.add(int(cols[7]))
    return uids


def _proc_address(hex_addr: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """An address as /proc/net/tcp* writes it: 32-bit words in the host's byte order."""
    raw = bytes.fromhex(hex_addr)
    if sys.byteorder == "little":
        raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    return ipaddress.ip_address(raw)

"""One-host authentication that costs the user nothing: zenoh's user/password transport
authentication with a password the server makes and keeps in a file only its user can read.

A server (the listening peer of the embedded default) creates, or reuses, a random password
per local endpoint it listens on, in `credentials_dir()/{protocol}-{port}.usrpwd` (mode 600
in a mode 700 directory; one line `minority:PASSWORD`, the format of zenoh's
`transport/auth/usrpwd/dictionary_file`). Clients of the same user that connect to a local
endpoint (127.0.0.1, localhost, ::1) read the file for that endpoint and authenticate. A peer
without the password is refused when it opens its link, before it can subscribe, put, query
or declare a liveliness token, so it can neither forge messages into a run nor read one.
The password is kept across server restarts, so ranks whose server restarts reconnect.

Why the transport and not a token in each message's header: every subscriber of a run sees
its headers, so a header token is known to any peer that can connect at all; refusing the
link to a peer without the password closes both reading and forging and adds nothing to a
message. Across hosts, use certificates and per-run access control (deploy/README.md), or
pass the same file to both sides with `--credentials FILE`.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path

AUTH_USER = "minority"
CREDENTIALS_ENV = "MINORITY_CREDENTIALS_DIR"  # overrides credentials_dir() (tests, services)
LOCAL_HOSTS = {"127.0.0.1", "localhost", "0.0.0.0", "::1", "::"}
_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z]+)/(?P<host>\[[^\]]*\]|[^:/]+):(?P<port>\d{1,5})")


class CredentialsError(OSError):
    """A credentials file that cannot be used (unsafe permissions, another owner, garbled)."""


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


def credentials_path(endpoint: str) -> Path | None:
    """The file of a local endpoint (`tcp/127.0.0.1:7447` -> `tcp-7447.usrpwd`); None for
    an endpoint on another host (its password is not ours to send)."""
    m = _ENDPOINT_RE.match(endpoint)
    if m is None or m["host"].strip("[]") not in LOCAL_HOSTS:
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


def client_credentials(connect: list[str]) -> Credentials | None:
    """The credentials for the first local endpoint in `connect` that has a file; None when
    there is none (the server then needs no password, or the connection is refused)."""
    for path in filter(None, map(credentials_path, connect)):
        if path.exists():
            return read_credentials(path)
    return None

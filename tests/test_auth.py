"""One-host authentication (protocol.auth): the server's password lives in a file only its
user can read; local clients send it; a peer without it cannot open a link, so it can neither
forge messages into a run nor read them; and a client sends nothing to a local endpoint it
cannot authenticate (no password file, another user's listener). Loopback only, bounded
waits."""

import os
import stat
import threading

import pytest
import zenoh
from conftest import free_port
from test_loopback import wait_until

from minority.protocol import auth, keys
from minority.protocol import session as session_module
from minority.protocol.auth import (
    CREDENTIALS_ENV,
    CredentialsError,
    credentials_path,
    read_credentials,
    server_credentials,
)
from minority.protocol.session import Inbox, NetworkOptions, Role, open_session


def test_the_server_makes_a_private_password_and_keeps_it_across_restarts(endpoint):
    first = server_credentials([endpoint])
    path = credentials_path(endpoint)
    assert first.path == path and first.user == "minority" and len(first.password) >= 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert server_credentials([endpoint]) == first  # a restart keeps it: ranks reconnect


def test_local_endpoints_share_a_file_and_remote_ones_have_none():
    assert credentials_path("tcp/127.0.0.1:7447") == credentials_path("tcp/localhost:7447") \
        == credentials_path("tcp/[::1]:7447") == credentials_path("tcp/0.0.0.0:7447")
    assert credentials_path("tcp/127.0.0.1:7448") != credentials_path("tcp/127.0.0.1:7447")
    # every address of this host is local: the rest of loopback, a name for it
    assert credentials_path("tcp/127.0.0.2:7447") == credentials_path("tcp/127.0.0.1:7447")
    assert credentials_path("tcp/[::ffff:127.0.0.1]:7447") == credentials_path("tcp/[::1]:7447")
    assert credentials_path("tcp/cluster-node-3:7447") is None
    assert credentials_path("not an endpoint") is None


def test_unsafe_or_garbled_credentials_are_refused(tmp_path):
    path = tmp_path / "creds"
    path.write_text("minority:pw\n")
    os.chmod(path, 0o644)
    with pytest.raises(CredentialsError, match="readable by others"):
        read_credentials(path)
    os.chmod(path, 0o600)
    assert read_credentials(path).password == "pw"
    path.write_text("no separator\n")
    with pytest.raises(CredentialsError, match="user:password"):
        read_credentials(path)


def test_a_peer_without_the_password_cannot_connect(server, endpoint, tmp_path, monkeypatch):
    """The server fixture opened with the embedded default: it requires the password."""
    inbox = Inbox(server, keys.everything("r"))
    with monkeypatch.context() as m:  # another user: no file of theirs to read
        m.setenv(CREDENTIALS_ENV, str(tmp_path / "elsewhere"))
        with pytest.raises(CredentialsError):  # their client does not send to our server...
            open_session(NetworkOptions(connect=[endpoint]), Role.CLIENT)
        with pytest.raises(zenoh.ZError):  # ... and forced, our server refuses it
            open_session(NetworkOptions(connect=[endpoint], auth=False), Role.CLIENT)
    wrong = tmp_path / "wrong"
    wrong.write_text("minority:guess\n")
    os.chmod(wrong, 0o600)
    with pytest.raises(zenoh.ZError):
        open_session(NetworkOptions(connect=[endpoint], credentials_file=wrong), Role.CLIENT)
    plain = zenoh.Config()
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("scouting/multicast/enabled", "false")
    plain.insert_json5("connect/endpoints", f'["{endpoint}"]')
    with pytest.raises(zenoh.ZError):  # a bare zenoh client, as any local process could open
        zenoh.open(plain)
    client = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5), Role.CLIENT)
    try:
        client.put(keys.event("r"), b"x")
        assert wait_until(lambda: inbox.received == 1)
    finally:
        client.close()


def test_a_server_without_auth_lets_clients_without_auth_in_and_leaves_no_file(endpoint):
    server_credentials([endpoint])  # a file from an earlier server on this endpoint
    server = open_session(NetworkOptions(listen=[endpoint], auth=False), Role.SERVER)
    try:
        assert not credentials_path(endpoint).exists()
        with pytest.raises(CredentialsError, match="no password file"):  # --no-auth on one side
            open_session(NetworkOptions(connect=[endpoint]), Role.CLIENT)
        client = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5,
                                             auth=False), Role.CLIENT)
        client.close()
    finally:
        server.close()


class Squatter:
    """Another user's zenoh peer on a local port: no password file, no authentication; it
    counts every sample, query and liveliness token that reaches it."""

    def __init__(self, endpoint: str):
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", "false")
        cfg.insert_json5("listen/endpoints", f'["{endpoint}"]')
        self.session = zenoh.open(cfg)
        self.heard: list[str] = []
        self._entities = [
            self.session.declare_subscriber("**", lambda s: self.heard.append(str(s.key_expr))),
            self.session.declare_queryable("**", lambda q: self.heard.append(f"?{q.key_expr}")),
            self.session.liveliness().declare_subscriber(
                "**", lambda s: self.heard.append(f"token {s.key_expr}"))]

    def peers(self) -> list:
        return list(self.session.info.peers_zid()) + list(self.session.info.routers_zid())

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def squatter(endpoint):
    s = Squatter(endpoint)
    yield s
    s.close()


@pytest.fixture
def no_session_opened(monkeypatch):
    """The zenoh sessions opened from now on (the squatter's is open already)."""
    opened = []
    real_open = zenoh.open
    monkeypatch.setattr(zenoh, "open", lambda cfg: opened.append(cfg) or real_open(cfg))
    return opened


def test_a_client_sends_nothing_to_a_local_endpoint_without_a_password_file(
        squatter, endpoint, no_session_opened):
    """Another user listens on the port first; this user has no password file for it (first
    use, after --no-auth, after the runtime directory was wiped): refused before any session
    opens, with the endpoint, the expected file and the fixes named."""
    with pytest.raises(CredentialsError) as refused:
        open_session(NetworkOptions(connect=[endpoint]), Role.CLIENT)
    text = str(refused.value)
    assert endpoint in text and str(credentials_path(endpoint)) in text
    assert "minority serve" in text and "--no-auth" in text and "--credentials" in text
    with pytest.raises(CredentialsError, match="waited 0.2 s"):  # --wait S: the file never came
        open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=0.2), Role.CLIENT)
    assert no_session_opened == [] and squatter.peers() == [] and squatter.heard == []


def test_the_in_situ_api_does_not_publish_to_a_squatter(squatter, endpoint, no_session_opened):
    """minority.insitu.connect (every sim's publisher): no session, so no token, no spec
    query, no Stats or events reach the squatter; the reason names the missing file."""
    from minority.insitu import connect

    viz = connect("r", connect=[endpoint], report=False)
    try:
        assert str(credentials_path(endpoint)) in viz.no_server_reason
    finally:
        viz.close()
    assert no_session_opened == [] and squatter.peers() == [] and squatter.heard == []


def test_a_client_started_before_its_server_waits_for_the_password_file(endpoint,
                                                                        monkeypatch):
    missed = threading.Event()
    real = session_module.with_credentials

    def with_credentials(opts, role):
        try:
            return real(opts, role)
        except CredentialsError:
            missed.set()
            raise

    monkeypatch.setattr(session_module, "with_credentials", with_credentials)
    opened: list = []
    client = threading.Thread(target=lambda: opened.append(open_session(
        NetworkOptions(connect=[endpoint], connect_timeout_s=30), Role.CLIENT)))
    client.start()
    assert missed.wait(10)  # it found no file, and keeps looking
    server = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    try:
        client.join(40)
        assert len(opened) == 1
        opened[0].close()
    finally:
        server.close()


def test_listener_owners_come_from_the_system(server, endpoint):
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("the system does not say who owns a socket (no /proc/net/tcp)")
    assert auth.listener_uids(endpoint) == {os.getuid()}
    port = endpoint.rsplit(":", 1)[1]
    assert auth.listener_uids(f"tcp/localhost:{port}") == {os.getuid()}
    assert auth.listener_uids(f"tcp/127.0.0.1:{free_port()}") == set()  # nobody listens


def test_a_stale_password_file_does_not_vouch_for_another_users_listener(
        server, endpoint, monkeypatch):
    """This user's server stopped (its file stays, for restarts) and another user took the
    port: the listener's owner gives it away."""
    monkeypatch.setattr(auth, "listener_uids", lambda e: {os.getuid() + 1})
    with pytest.raises(auth.ForeignServerError, match="another user"):
        open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5), Role.CLIENT)
    open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5, auth=False),
                 Role.CLIENT).close()  # --no-auth: the user's call

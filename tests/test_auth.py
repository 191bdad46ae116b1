"""One-host authentication (protocol.auth): the server's password lives in a file only its
user can read; local clients send it; a peer without it cannot open a link, so it can neither
forge messages into a run nor read them. Loopback only, bounded waits."""

import os
import stat

import pytest
import zenoh
from minority.protocol import keys
from minority.protocol.auth import (
    CREDENTIALS_ENV,
    CredentialsError,
    credentials_path,
    read_credentials,
    server_credentials,
)
from minority.protocol.session import Inbox, NetworkOptions, Role, open_session
from test_loopback import wait_until


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
        with pytest.raises(zenoh.ZError):
            open_session(NetworkOptions(connect=[endpoint]), Role.CLIENT)
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


def test_a_server_without_auth_lets_clients_in_and_leaves_no_file(endpoint):
    server_credentials([endpoint])  # a file from an earlier server on this endpoint
    server = open_session(NetworkOptions(listen=[endpoint], auth=False), Role.SERVER)
    try:
        assert not credentials_path(endpoint).exists()
        client = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5),
                              Role.CLIENT)
        client.close()
    finally:
        server.close()

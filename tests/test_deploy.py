"""deploy/: every zenoh config parses with the installed zenoh and the one-host files equal
the embedded defaults; a put crosses a one-host session pair; the router's TLS + access
control lets only the ranks' certificate put chunks (a router, server, rank and viewer
opened on loopback with certificates from deploy/tls/make-certs.sh); user/password
identities get the same rules; the systemd unit and the shell scripts are well formed.

Loopback only, multicast scouting off, every wait bounded (events and round trips, no
sleeps)."""

from __future__ import annotations

import configparser
import json
import shlex
import shutil
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh
from conftest import free_port

from minority.cli import build_parser
from minority.protocol import keys
from minority.protocol.session import NetworkOptions, Role, make_config, open_session

ROOT = Path(__file__).parent.parent
DEPLOY = ROOT / "deploy"
ZENOH_FILES = sorted((DEPLOY / "zenoh").glob("*.json5"))
SHELL_SCRIPTS = [DEPLOY / "tls" / "make-certs.sh", DEPLOY / "tls" / "make-run-certs.sh",
                 DEPLOY / "slurm" / "minority.sbatch"]
UNIT = DEPLOY / "systemd" / "minority-serve.service"
RUN = "deploy-test"
TIMEOUT_S = 10.0


def get(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


# --- files -----------------------------------------------------------------------------------
def test_expected_files_exist():
    names = {p.name for p in ZENOH_FILES}
    assert {"one-host.json5", "router.json5", "server.json5", "rank.json5"} <= names
    for path in [*SHELL_SCRIPTS, UNIT, DEPLOY / "README.md"]:
        assert path.is_file(), path


@pytest.mark.parametrize("path", ZENOH_FILES, ids=lambda p: p.name)
def test_zenoh_config_parses(path):
    """zenoh rejects unknown keys and values, so this checks the schema against zenoh 1.10."""
    cfg = zenoh.Config.from_file(str(path))
    assert get(cfg, "scouting/multicast/enabled") is False
    assert get(cfg, "scouting/gossip/enabled") is False
    for value in json.loads(cfg.get_json("transport/link/tls")).values():
        assert not isinstance(value, str) or value.startswith("deploy/tls/"), value


def test_one_host_files_equal_the_embedded_defaults():
    from minority.insitu.publisher import BLOCK_TIMEOUT_KEY, BLOCK_TIMEOUT_S

    server = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "one-host.json5"))
    assert json.loads(str(server)) == json.loads(str(make_config(NetworkOptions(), Role.SERVER)))
    client = make_config(NetworkOptions(), Role.CLIENT)
    client.insert_json5(BLOCK_TIMEOUT_KEY, str(int(BLOCK_TIMEOUT_S * 1e6)))  # as `minority sim`
    assert json.loads(str(zenoh.Config.from_file(str(DEPLOY / "zenoh" / "one-host-client.json5")))) \
        == json.loads(str(client))


# --- waiting ---------------------------------------------------------------------------------
class Seen:
    """Keys a subscriber received, with a bounded wait for one of them."""

    def __init__(self):
        self.keys: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            deleted = sample.kind == zenoh.SampleKind.DELETE  # e.g. a liveliness token gone
            self.keys.append(f"DELETE:{sample.key_expr}" if deleted else str(sample.key_expr))
            self._cond.notify_all()

    def wait_for(self, key: str, timeout_s: float = TIMEOUT_S) -> bool:
        return self.wait_count(key, 1, timeout_s)

    def wait_count(self, key: str, n: int, timeout_s: float = TIMEOUT_S) -> bool:
        """Wait (bounded) until `key` has arrived at least `n` times."""
        with self._cond:
            return self._cond.wait_for(lambda: self.keys.count(key) >= n, timeout_s)


def put_until_seen(session: zenoh.Session, key: str, seen: Seen, tries: int = 20) -> None:
    """Put `key` until `seen` has it (routes take a moment to settle): at most `tries` puts,
    each followed by a bounded wait."""
    for _ in range(tries):
        session.put(key, b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        if seen.wait_for(key, TIMEOUT_S / tries):
            return
    raise AssertionError(f"{key} never arrived; seen: {seen.keys}")


# --- one host ----------------------------------------------------------------------------------
def test_one_host_put_reaches_subscriber():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(NetworkOptions(config=DEPLOY / "zenoh" / "one-host.json5",
                                         listen=[endpoint]), Role.SERVER)
    try:
        seen = Seen()
        sub = server.declare_subscriber(keys.chunks(RUN), seen)
        client = open_session(NetworkOptions(config=DEPLOY / "zenoh" / "one-host-client.json5",
                                             connect=[endpoint], connect_timeout_s=5), Role.CLIENT)
        try:
            put_until_seen(client, keys.chunk(RUN, 1, 0), seen)
        finally:
            client.close()
        sub.undeclare()
    finally:
        server.close()


# --- several hosts: TLS and access control, on loopback -------------------------------------
def make_certs(tmp_path_factory) -> Path:
    """make-certs.sh's test CA and role certificates in a new directory (skips without openssl)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl not found: cannot generate the test certificates for the TLS/ACL test")
    out = tmp_path_factory.mktemp("tls")
    subprocess.run(["bash", str(DEPLOY / "tls" / "make-certs.sh"), str(out)], check=True,
                   capture_output=True, timeout=60)
    return out


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    return make_certs(tmp_path_factory)


def local_copy(name: str, certs: Path, tmp: Path, loopback_readers: bool = True) -> Path:
    """deploy/zenoh/NAME with deploy/tls/ replaced by `certs` (what minority.sbatch does).

    Every test session arrives over loopback, and router.json5 lets loopback sessions read
    (subject "local"); without `loopback_readers` that subject matches no interface, so the
    certificates alone decide and each rule is tested on its own."""
    text = (DEPLOY / "zenoh" / name).read_text().replace('"deploy/tls/', f'"{certs}/')
    if not loopback_readers:
        assert text.count('interfaces: ["lo"]') == 1
        text = text.replace('interfaces: ["lo"]', 'interfaces: ["no-such-interface"]')
    path = tmp / name
    path.write_text(text)
    return path


def open_router(certs: Path, tmp: Path, usrpwd: dict | None = None,
                loopback_readers: bool = True):
    tls_port, tcp_port = free_port(), free_port()
    cfg = zenoh.Config.from_file(str(local_copy("router.json5", certs, tmp, loopback_readers)))
    cfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{tls_port}",
                                                     f"tcp/127.0.0.1:{tcp_port}"]))
    if usrpwd is not None:
        dictionary = tmp / "credentials.txt"
        dictionary.write_text("".join(f"{u}:{p}\n" for u, p in usrpwd.items()))
        cfg.insert_json5("transport/auth/usrpwd", json.dumps({"dictionary_file": str(dictionary)}))
    return zenoh.open(cfg), f"tls/127.0.0.1:{tls_port}", f"tcp/127.0.0.1:{tcp_port}"


def open_client(name: str, certs: Path, tmp: Path, endpoint: str, role: Role = Role.CLIENT,
                user: tuple[str, str] | None = None) -> zenoh.Session:
    """A session as the commands open it: --config FILE --connect ENDPOINT."""
    cfg = make_config(NetworkOptions(config=local_copy(name, certs, tmp), connect=[endpoint]),
                      role)
    if user is not None:
        cfg.insert_json5("transport/auth/usrpwd", json.dumps({"user": user[0], "password": user[1]}))
    return zenoh.open(cfg)


class Deployment:
    """Router + render server + viewer + rank, as router.json5/server.json5/... describe."""

    def __init__(self, certs: Path, tmp: Path):
        self.closing: list = []
        self.router, self.tls, self.tcp = open_router(certs, tmp, loopback_readers=False)
        self.closing.append(self.router)
        self.spec_queries = 0
        # the server: what render_server/daemon.py declares, plus a subscriber for all
        self.server = self._open("server.json5", certs, tmp, Role.SERVER)
        self.server_seen, self.server_tokens = Seen(), Seen()
        self.server.declare_subscriber(keys.chunks(RUN), self.server_seen)
        self.server.declare_subscriber(keys.event(RUN), self.server_seen)
        self.server.declare_subscriber(keys.stats(RUN), self.server_seen)
        self.server.declare_queryable(keys.spec(RUN), self._on_query)
        self.server.liveliness().declare_subscriber(keys.rank_tokens(RUN), self.server_tokens,
                                                    history=True)
        # a read-only viewer that sees everything of the run (a recorder)
        self.viewer = self._open("viewer.json5", certs, tmp)
        self.viewer_seen = Seen()
        self.viewer.declare_subscriber(keys.everything(RUN), self.viewer_seen)
        # the rank follows spec updates, as minority.insitu does
        self.rank = self._open("rank.json5", certs, tmp)
        self.rank_seen = Seen()
        self.rank.declare_subscriber(keys.spec(RUN), self.rank_seen)
        # a second viewer without subscribers: an intruder whose puts nobody local receives
        self.intruder = self._open("viewer.json5", certs, tmp)

    def _open(self, name, certs, tmp, role=Role.CLIENT):
        session = open_client(name, certs, tmp, self.tls, role)
        self.closing.append(session)
        return session

    def _on_query(self, query: zenoh.Query) -> None:
        self.spec_queries += 1
        query.reply(keys.spec(RUN), b"the spec")

    def close(self):
        for session in reversed(self.closing):
            session.close()


@pytest.fixture(scope="module")
def deployment(certs, tmp_path_factory):
    d = Deployment(certs, tmp_path_factory.mktemp("deploy"))
    # routes settled: a rank chunk reaches the server and the viewer
    put_until_seen(d.rank, keys.chunk(RUN, 0, 0), d.viewer_seen)
    assert d.server_seen.wait_for(keys.chunk(RUN, 0, 0))
    yield d
    d.close()


def spec_replies(session: zenoh.Session) -> list[bytes]:
    """Every reply (no consolidation: replies on the same key are all kept)."""
    return [r.ok.payload.to_bytes() for r in session.get(
        keys.spec(RUN), timeout=TIMEOUT_S, consolidation=zenoh.ConsolidationMode.NONE)
        if r.ok is not None]


def test_tls_identities_reach_the_router(deployment):
    for session in (deployment.server, deployment.viewer, deployment.rank, deployment.intruder):
        assert [str(z) for z in session.info.routers_zid()] == [str(deployment.router.zid())]


def test_rank_publishes_chunks_events_stats_and_token_and_gets_the_spec(deployment):
    d = deployment
    assert spec_replies(d.rank) == [b"the spec"]
    token = d.rank.liveliness().declare_token(keys.rank_token(RUN, 3))
    assert d.server_tokens.wait_for(keys.rank_token(RUN, 3))
    d.rank.put(keys.chunk(RUN, 5, 3), b"chunk", congestion_control=zenoh.CongestionControl.BLOCK)
    d.rank.put(keys.event(RUN), b"rank_done", congestion_control=zenoh.CongestionControl.BLOCK)
    d.rank.put(keys.stats(RUN), b"stats", congestion_control=zenoh.CongestionControl.BLOCK)
    assert d.server_seen.wait_for(keys.chunk(RUN, 5, 3))
    assert d.server_seen.wait_for(keys.event(RUN))
    assert d.server_seen.wait_for(keys.stats(RUN))  # minority.insitu's flow statistics
    assert d.viewer_seen.wait_for(keys.event(RUN))
    token.undeclare()
    assert d.server_tokens.wait_for(f"DELETE:{keys.rank_token(RUN, 3)}")


def test_rank_publisher_sees_the_server_subscriber(deployment):
    """Matching status crosses the router (rule "see-readers")."""
    publisher = deployment.rank.declare_publisher(keys.chunk(RUN, 7, 0))
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda s: s.matching and matched.set())
    try:
        assert matched.wait(TIMEOUT_S) or publisher.matching_status.matching
    finally:
        listener.undeclare()
        publisher.undeclare()


def test_server_publishes_frames_timing_and_spec(deployment):
    d = deployment
    for key in (keys.frame(RUN, "side"), keys.timing(RUN), keys.spec(RUN)):
        d.server.put(key, b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        assert d.viewer_seen.wait_for(key), key
    assert d.rank_seen.wait_for(keys.spec(RUN))  # ranks follow spec updates


def denied_then_allowed(putter: zenoh.Session, denied: str, allowed: str, seen: Seen) -> None:
    """`denied` and then `allowed`, from one session, same priority and congestion control:
    they travel in order over one link and the router forwards in order, so once `allowed`
    has arrived, `denied` would have arrived before it had the router let it through."""
    start, before = len(seen.keys), seen.keys.count(allowed)  # `allowed` may have come before
    for _ in range(20):
        putter.put(denied, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
        putter.put(allowed, b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        if seen.wait_count(allowed, before + 1, TIMEOUT_S / 20):
            break
    assert seen.wait_count(allowed, before + 1, 0)
    assert denied not in seen.keys[start:]


def test_rank_cannot_put_frames_timing_or_spec(deployment):
    d = deployment
    for i, key in enumerate((keys.frame(RUN, "side"), keys.timing(RUN), keys.spec(RUN))):
        denied_then_allowed(d.rank, key, keys.chunk(RUN, 100 + i, 0), d.viewer_seen)


def test_only_ranks_may_put_chunks(deployment):
    d = deployment
    # the server's certificate: allowed frames, not chunks
    denied_then_allowed(d.server, keys.chunk(RUN, 200, 9), keys.frame(RUN, "top"), d.viewer_seen)
    # the viewer's certificate: no put at all. Its put is followed by a get of the spec (a
    # round trip through the router on the same link), then by a rank's put: had the router
    # forwarded the viewer's, it would arrive first.
    forged = keys.chunk(RUN, 201, 9)
    d.intruder.put(forged, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
    assert spec_replies(d.intruder) == [b"the spec"]
    marker = keys.chunk(RUN, 201, 0)
    put_until_seen(d.rank, marker, d.server_seen)
    assert d.viewer_seen.wait_for(marker)
    assert forged not in d.server_seen.keys and forged not in d.viewer_seen.keys


def test_loopback_clients_without_certificate_only_read(certs, tmp_path):
    """router.json5's tcp/127.0.0.1 listener: no identity, read-only (subject "local")."""
    router, tls, tcp = open_router(certs, tmp_path)
    sessions = [router]
    try:
        reader = zenoh.open(make_config(NetworkOptions(connect=[tcp]), Role.CLIENT))
        sessions.append(reader)
        seen = Seen()
        reader.declare_subscriber(keys.everything(RUN), seen)
        intruder = zenoh.open(make_config(NetworkOptions(connect=[tcp]), Role.CLIENT))
        sessions.append(intruder)
        rank = open_client("rank.json5", certs, tmp_path, tls)
        sessions.append(rank)
        put_until_seen(rank, keys.chunk(RUN, 1, 0), seen)  # it reads
        forged = keys.chunk(RUN, 2, 9)
        intruder.put(forged, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
        spec_replies(intruder)  # round trip: the router has handled the put
        put_until_seen(rank, keys.chunk(RUN, 3, 0), seen)
        assert forged not in seen.keys
    finally:
        for session in reversed(sessions):
            session.close()


def test_only_the_server_serves_the_spec(deployment):
    d = deployment
    forged = d.rank.declare_queryable(keys.spec(RUN), lambda q: q.reply(keys.spec(RUN), b"forged"))
    try:
        spec_replies(d.rank)  # a round trip after the declaration, on the same link
        assert spec_replies(d.viewer) == [b"the spec"]
    finally:
        forged.undeclare()


def test_usernames_identify_clients_too(certs, tmp_path):
    """The same rules by user/password (router with a dictionary; then every client needs
    credentials, certificate or not)."""
    router, tls, tcp = open_router(certs, tmp_path, usrpwd={
        "minority-rank": "rank-pw", "minority-viewer": "viewer-pw"}, loopback_readers=False)
    sessions = [router]
    try:
        with pytest.raises(zenoh.ZError):  # a certificate alone is not enough any more
            sessions.append(open_client("rank.json5", certs, tmp_path, tls))
        with pytest.raises(zenoh.ZError):  # nor a wrong password
            sessions.append(open_client("one-host-client.json5", certs, tmp_path, tcp,
                                        user=("minority-rank", "wrong")))

        def login(user, password):
            session = open_client("one-host-client.json5", certs, tmp_path, tcp,
                                  user=(user, password))
            sessions.append(session)
            return session

        reader, intruder = login("minority-viewer", "viewer-pw"), login("minority-viewer", "viewer-pw")
        seen = Seen()
        reader.declare_subscriber(keys.everything(RUN), seen)
        rank = login("minority-rank", "rank-pw")
        put_until_seen(rank, keys.chunk(RUN, 1, 0), seen)
        # a viewer's put of a chunk is dropped by the router: its put, then a round trip
        # through the router on the same link, then a rank's put that does arrive
        forged = keys.chunk(RUN, 2, 9)
        intruder.put(forged, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
        spec_replies(intruder)
        put_until_seen(rank, keys.chunk(RUN, 3, 0), seen)
        assert forged not in seen.keys
    finally:
        for session in reversed(sessions):
            session.close()


# --- systemd and shell ------------------------------------------------------------------------
def test_systemd_unit_is_complete():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # systemd keys are case sensitive
    unit.read(UNIT)
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    service = unit["Service"]
    for key in ("User", "Group", "WorkingDirectory", "Environment", "ExecStart", "Restart"):
        assert service.get(key), key
    assert service["Restart"] == "on-failure"
    assert service["User"] not in ("root", "0")
    assert unit["Install"]["WantedBy"] == "multi-user.target"
    # Environment= repeats (configparser keeps the last one): read them from the lines
    env = {}
    for line in UNIT.read_text().splitlines():
        if line.startswith("Environment="):
            name, _, value = line.removeprefix("Environment=").partition("=")
            env[name] = value
    assert {"MINORITY_SPEC", "MINORITY_OUT", "MINORITY_ZENOH_CONFIG"} <= set(env)
    assert env["MINORITY_ZENOH_CONFIG"].endswith(".json5")
    # ExecStart as systemd expands it: ${VAR} is one word, $VAR splits (empty: no word)
    argv = []
    for word in shlex.split(service["ExecStart"]):
        if word.startswith("${"):
            argv.append(env[word[2:-1]])
        elif word.startswith("$"):
            argv.extend(env[word[1:]].split())
        else:
            argv.append(word)
    assert argv[0].endswith("/python") and argv[1:4] == ["-m", "minority", "serve"]
    # the flags exist: the real `minority` parser accepts them
    args = build_parser().parse_args(argv[3:])
    assert args.command == "serve" and str(args.config) == env["MINORITY_ZENOH_CONFIG"]


@pytest.mark.parametrize("script", SHELL_SCRIPTS, ids=lambda p: p.name)
def test_shell_scripts_parse(script):
    result = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True,
                            timeout=30)
    assert result.returncode == 0, result.stderr


def test_make_certs_common_names(certs):
    for name, cn in (("router", "minority-router"), ("server", "minority-server"),
                     ("rank", "minority-rank"), ("viewer", "minority-viewer")):
        subject = subprocess.run(["openssl", "x509", "-in", str(certs / f"{name}.crt"),
                                  "-noout", "-subject"], capture_output=True, text=True,
                                 check=True, timeout=30).stdout
        assert f"CN = {cn}" in subject or f"CN={cn}" in subject, subject

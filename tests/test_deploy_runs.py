"""Per-run access control (protocol/acl.py, `minority deploy acl`, deploy/tls/make-run-certs.sh).

The generated rules name each run's key expressions literally; a router (opened in process, as
tests/test_deploy.py does) serving runs A and B with certificates of make-run-certs.sh lets
run A's rank certificate put chunks, events and stats, hold its token and read the spec of A,
and nothing of B; the same by user name; a per-run viewer reads its run only; the role-wide
rank certificate of make-certs.sh may do nothing.

Loopback only, multicast scouting off, every wait bounded: a denied message is followed by an
allowed one on the same link (the router handles a link's messages in order and forwards them
in order), and the test waits for the allowed one, never on a sleep."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh
from conftest import free_port
from test_deploy import TIMEOUT_S, Seen, denied_then_allowed, make_certs, put_until_seen

from minority import deploy_cli
from minority.protocol import keys
from minority.protocol.acl import (
    ConfigTextError,
    identity,
    router_access_control,
    router_config_text,
)
from minority.protocol.session import NetworkOptions, Role, make_config

ROOT = Path(__file__).parent.parent
DEPLOY = ROOT / "deploy"
MAKE_RUN_CERTS = DEPLOY / "tls" / "make-run-certs.sh"
A, B = "run-a", "run_b.2"  # run ids with the characters a run id may have


def ac(config: zenoh.Config) -> dict:
    return json.loads(config.get_json("access_control"))


def without_nulls(obj):
    """zenoh fills absent optional fields with null: compare without them."""
    if isinstance(obj, dict):
        return {k: without_nulls(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [without_nulls(v) for v in obj]
    return obj


# --- the generated rules -------------------------------------------------------------------------
def test_identities_name_the_run():
    assert identity("rank", "column") == "minority-rank.column"
    assert identity("viewer", A) == f"minority-viewer.{A}"
    assert identity("server") == "minority-server"
    for role, run in (("admin", "column"), ("rank", "*"), ("rank", "a/b"), ("rank", "")):
        with pytest.raises(ValueError):
            identity(role, run)


def test_every_rule_names_one_listed_run():
    acl = router_access_control([A, B, A])
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert len(rules) == len(acl["rules"]) and len(subjects) == len(acl["subjects"])
    for rule in acl["rules"]:
        assert rule["permission"] == "allow"
        run = rule["id"].split(".", 1)[1]
        assert run in (A, B)
        for key_expr in rule["key_exprs"]:
            assert key_expr.startswith(f"minority/{run}/"), key_expr
    policies = {p["id"]: p for p in acl["policies"]}
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules) and set(policy["subjects"]) <= set(subjects)
    # a run's rank identity: its run's rules only, no read of the whole run
    for run in (A, B):
        rank = policies[f"rank.{run}"]
        assert {subjects[s].get("cert_common_names", subjects[s].get("usernames"))[0]
                for s in rank["subjects"]} == {f"minority-rank.{run}"}
        assert all(r.endswith(f".{run}") for r in rank["rules"])
        assert f"read.{run}" not in rank["rules"] and f"server-put.{run}" not in rank["rules"]
    # no role-wide rank identity; role-wide server and viewers and loopback readers of both runs
    names = [n for s in acl["subjects"] for n in s.get("cert_common_names", []) + s.get("usernames", [])]
    assert "minority-rank" not in names
    assert "minority-server" in names and "minority-viewer" in names
    assert {r.split(".", 1)[1] for r in policies["local"]["rules"]} == {A, B}
    assert f"server-put.{A}" in policies["server"]["rules"]
    assert f"server-put.{A}" not in policies["viewer"]["rules"]
    # the oracle of a run: the spec updates of that run and a viewer's reading, no chunks
    oracle = set(policies[f"oracle.{A}"]["rules"])
    assert oracle == {f"{r}.{A}" for r in ("oracle-put", "read", "read-out", "spec-read",
                                           "spec-read-out", "see-readers")}
    assert rules[f"oracle-put.{A}"]["key_exprs"] == [f"minority/{A}/spec"]


def test_options_drop_shared_identities_loopback_and_usernames():
    acl = router_access_control([A], shared=(), loopback_readers=False, usernames=False)
    assert {p["id"] for p in acl["policies"]} == {f"rank.{A}", f"server.{A}", f"viewer.{A}",
                                                  f"oracle.{A}"}
    assert all(set(s) == {"id", "cert_common_names"} for s in acl["subjects"])


@pytest.mark.parametrize("runs, kwargs, error", [
    ([], {}, ValueError), ("column", {}, TypeError), (["*"], {}, ValueError),
    (["minority/x"], {}, ValueError), (["-x"], {}, ValueError), (["x" * 65], {}, ValueError),
    ([A], {"shared": ["rank"]}, ValueError), ([A], {"shared": ["admin"]}, ValueError),
    ([A], {"shared": "server"}, TypeError)])
def test_bad_runs_and_roles_are_refused(runs, kwargs, error):
    with pytest.raises(error):
        router_access_control(runs, **kwargs)


def test_zenoh_accepts_the_rules():
    acl = router_access_control([A, B])
    cfg = zenoh.Config()
    cfg.insert_json5("access_control", json.dumps(acl))  # zenoh rejects unknown keys
    assert without_nulls(ac(cfg)) == acl


# --- into the router config ------------------------------------------------------------------------
def test_router_config_keeps_everything_but_the_access_control():
    base_path = DEPLOY / "zenoh" / "router.json5"
    acl = router_access_control([A])
    text = router_config_text(base_path.read_text(), acl, "generated\nfor run-a")
    assert text.startswith("// generated\n// for run-a\n")
    assert "close a link when the peer's certificate expires" in text  # comments stay
    new, old = zenoh.Config.from_json5(text), zenoh.Config.from_file(str(base_path))
    assert without_nulls(ac(new)) == acl
    for key in ("mode", "listen", "connect", "scouting", "transport"):
        assert json.loads(new.get_json(key)) == json.loads(old.get_json(key)), key


@pytest.mark.parametrize("base", [
    '{mode: "router"}',
    '{mode: "router",}',
    "{}",
    '// c\n{\n  "mode": "router", /* access_control: {x} */ listen: {endpoints: ["tcp/127.0.0.1:7447"]}\n}\n',
    "{'access_control': {enabled: false, rules: [{id: 'x}]'}]}, mode: 'router'}",
    '{access_control: null, mode: "router"}',
])
def test_router_config_text_edits_json5(base):
    acl = router_access_control([A], loopback_readers=False)
    cfg = zenoh.Config.from_json5(router_config_text(base, acl))
    assert without_nulls(ac(cfg)) == acl
    if "mode" in base:
        assert json.loads(cfg.get_json("mode")) == "router"


@pytest.mark.parametrize("base", ["", "[1]", "{mode: ", '{"mode": "router"', "{mode 'x'}"])
def test_router_config_text_refuses_what_it_cannot_read(base):
    with pytest.raises(ConfigTextError):
        router_config_text(base, router_access_control([A]))


def test_cli_writes_a_router_config(tmp_path, capsys):
    out = tmp_path / "router-ab.json5"
    assert deploy_cli.main(["acl", "--run", A, "--run", B, "--router",
                            str(DEPLOY / "zenoh" / "router.json5"), "-o", str(out)]) == 0
    cfg = zenoh.Config.from_file(str(out))
    assert without_nulls(ac(cfg)) == router_access_control([A, B])
    assert out.read_text().startswith("// Generated by `minority deploy acl`")
    # without --router: the access_control object, for zenohd --cfg "access_control:..."
    assert deploy_cli.main(["acl", "--run", A, "--no-shared-server", "--no-shared-viewer",
                            "--no-loopback-readers", "--no-usernames"]) == 0
    assert json.loads(capsys.readouterr().out) == router_access_control(
        [A], shared=(), loopback_readers=False, usernames=False)
    assert deploy_cli.main(["acl", "--run", "a/b"]) == 2
    assert "run" in capsys.readouterr().err
    assert deploy_cli.main(["acl", "--run", A, "--router", str(tmp_path / "missing.json5")]) == 2


def test_cli_hooks_into_a_subparsers_object():
    """What minority/cli.py's build_parser does with it."""
    parser = argparse.ArgumentParser(prog="minority")
    deploy_cli.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["deploy", "acl", "--run", A, "--run", B, "-o", "x.json5"])
    assert args.command == "deploy" and args.run == [A, B] and args.func is deploy_cli._cmd_acl


# --- certificates per run ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """make-certs.sh's CA and role-wide certificates, then run certificates of A and B."""
    out = make_certs(tmp_path_factory)
    for args in ([A, "rank", "viewer", "oracle"], [B]):  # B: the default role, rank
        subprocess.run(["bash", str(MAKE_RUN_CERTS), str(out), *args], check=True,
                       capture_output=True, timeout=60)
    return out


def common_name(path: Path) -> str:
    subject = subprocess.run(["openssl", "x509", "-in", str(path), "-noout", "-subject",
                              "-nameopt", "multiline"], capture_output=True, text=True,
                             check=True, timeout=30).stdout
    return next(line.split("=", 1)[1].strip() for line in subject.splitlines()
                if line.strip().startswith("commonName"))


def test_make_run_certs(certs):
    for role, run in (("rank", A), ("viewer", A), ("oracle", A), ("rank", B)):
        crt, key = certs / f"{role}.{run}.crt", certs / f"{role}.{run}.key"
        assert common_name(crt) == identity(role, run)
        assert stat.S_IMODE(key.stat().st_mode) == 0o600
        subprocess.run(["openssl", "verify", "-CAfile", str(certs / "ca.crt"), str(crt)],
                       check=True, capture_output=True, timeout=30)
    assert not (certs / f"viewer.{B}.crt").exists()


@pytest.mark.parametrize("args, message", [
    (["*"], "run id"), (["a/b"], "run id"), ([".hidden"], "run id"), (["-x"], "run id"),
    ([A, "admin"], "ROLE"), ([], "usage")])
def test_make_run_certs_refuses(certs, args, message):
    result = subprocess.run(["bash", str(MAKE_RUN_CERTS), str(certs), *args],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and message in result.stderr, result.stderr


def test_make_run_certs_needs_the_ca(tmp_path):
    if shutil.which("openssl") is None:
        pytest.skip("openssl not found")
    result = subprocess.run(["bash", str(MAKE_RUN_CERTS), str(tmp_path), A],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and "make-certs.sh" in result.stderr
    assert os.listdir(tmp_path) == []


# --- a router serving runs A and B, in process, on loopback -------------------------------------------
def local_copy(name: str, certs: Path, tmp: Path, run: str | None = None) -> Path:
    """deploy/zenoh/NAME pointed at `certs`; with `run`, at its role's run certificate (the
    sed line of deploy/README.md: deploy/tls/rank. -> deploy/tls/rank.RUN.)."""
    text = (DEPLOY / "zenoh" / name).read_text()
    if run is not None:
        role = name.removesuffix(".json5")
        assert text.count(f'"deploy/tls/{role}.') == 2
        text = text.replace(f'"deploy/tls/{role}.', f'"deploy/tls/{role}.{run}.')
    path = tmp / (name if run is None else f"{run}-{name}")
    path.write_text(text.replace('"deploy/tls/', f'"{certs}/'))
    return path


def open_router(certs: Path, tmp: Path, runs: list[str], usrpwd: dict | None = None, **acl_kw):
    """router.json5 with the access control `minority deploy acl --run ... --router` writes."""
    text = router_config_text(local_copy("router.json5", certs, tmp).read_text(),
                              router_access_control(runs, **acl_kw))
    cfg = zenoh.Config.from_json5(text)
    tls_port, tcp_port = free_port(), free_port()
    cfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{tls_port}",
                                                     f"tcp/127.0.0.1:{tcp_port}"]))
    if usrpwd is not None:
        dictionary = tmp / "credentials.txt"
        dictionary.write_text("".join(f"{u}:{p}\n" for u, p in usrpwd.items()))
        cfg.insert_json5("transport/auth/usrpwd", json.dumps({"dictionary_file": str(dictionary)}))
    return zenoh.open(cfg), f"tls/127.0.0.1:{tls_port}", f"tcp/127.0.0.1:{tcp_port}"


def open_client(config: Path, endpoint: str, role: Role = Role.CLIENT,
                user: tuple[str, str] | None = None) -> zenoh.Session:
    cfg = make_config(NetworkOptions(config=config, connect=[endpoint]), role)
    if user is not None:
        cfg.insert_json5("transport/auth/usrpwd", json.dumps({"user": user[0], "password": user[1]}))
    return zenoh.open(cfg)


class Counting(Seen):
    """Seen, with the payloads too: (key, payload) in arrival order."""

    def __init__(self):
        super().__init__()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
        super().__call__(sample)

    def wait_item(self, key: str, payload: bytes, timeout_s: float = TIMEOUT_S) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: (key, payload) in self.items, timeout_s)


class TwoRuns:
    """A router serving runs A and B (loopback readers off: the certificates alone decide),
    the role-wide render server serving both, a rank of each run, a viewer of run A."""

    def __init__(self, certs: Path, tmp: Path):
        self.certs, self.tmp = certs, tmp
        self.closing: list = []
        self.router, self.tls, _ = open_router(certs, tmp, [A, B], loopback_readers=False)
        self.closing.append(self.router)
        self.server = self.open(local_copy("server.json5", certs, tmp), Role.SERVER)
        self.server_seen, self.server_tokens = Counting(), Seen()
        self.queries = {A: 0, B: 0}
        for run in (A, B):
            for key in (keys.chunks(run), keys.event(run), keys.stats(run)):
                self.server.declare_subscriber(key, self.server_seen)
            self.server.declare_queryable(keys.spec(run), self._on_query)
            self.server.liveliness().declare_subscriber(keys.rank_tokens(run), self.server_tokens,
                                                        history=True)
        self.rank_a = self.open(local_copy("rank.json5", certs, tmp, A))
        self.rank_b = self.open(local_copy("rank.json5", certs, tmp, B))
        # rank A follows the spec of B (denied), then of A, as minority.insitu follows its own
        self.rank_a_seen = Counting()
        self.rank_a.declare_subscriber(keys.spec(B), self.rank_a_seen)
        self.rank_a.declare_subscriber(keys.spec(A), self.rank_a_seen)
        # a viewer of run A subscribes to all of B (denied), then all of A
        self.viewer_a = self.open(local_copy("viewer.json5", certs, tmp, A))
        self.viewer_a_seen = Counting()
        self.viewer_a.declare_subscriber(keys.everything(B), self.viewer_a_seen)
        self.viewer_a.declare_subscriber(keys.everything(A), self.viewer_a_seen)
        # routes settled: each rank's chunk reaches the server, A's reaches the viewer
        put_until_seen(self.rank_a, keys.chunk(A, 0, 0), self.viewer_a_seen)
        assert self.server_seen.wait_for(keys.chunk(A, 0, 0))
        put_until_seen(self.rank_b, keys.chunk(B, 0, 0), self.server_seen)

    def open(self, config: Path, role: Role = Role.CLIENT) -> zenoh.Session:
        session = open_client(config, self.tls, role)
        self.closing.append(session)
        return session

    def _on_query(self, query: zenoh.Query) -> None:
        run = keys.parse(str(query.key_expr)).run
        self.queries[run] += 1
        query.reply(keys.spec(run), f"spec {run}".encode())

    def close(self):
        for session in reversed(self.closing):
            session.close()


@pytest.fixture(scope="module")
def two_runs(certs, tmp_path_factory):
    d = TwoRuns(certs, tmp_path_factory.mktemp("runs"))
    yield d
    d.close()


def spec_replies(session: zenoh.Session, run: str) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(
        keys.spec(run), timeout=TIMEOUT_S, consolidation=zenoh.ConsolidationMode.NONE)
        if r.ok is not None]


def test_run_certificates_reach_the_router(two_runs):
    d = two_runs
    for session in (d.server, d.rank_a, d.rank_b, d.viewer_a):
        assert [str(z) for z in session.info.routers_zid()] == [str(d.router.zid())]


def test_rank_of_a_publishes_into_a(two_runs):
    d = two_runs
    assert spec_replies(d.rank_a, A) == [f"spec {A}".encode()]
    token = d.rank_a.liveliness().declare_token(keys.rank_token(A, 3))
    assert d.server_tokens.wait_for(keys.rank_token(A, 3))
    for key in (keys.chunk(A, 5, 3), keys.event(A), keys.stats(A)):
        d.rank_a.put(key, b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        assert d.server_seen.wait_for(key), key
        assert d.viewer_a_seen.wait_for(key), key
    token.undeclare()
    assert d.server_tokens.wait_for(f"DELETE:{keys.rank_token(A, 3)}")


def test_rank_of_a_cannot_put_into_b(two_runs):
    d = two_runs
    for i, key in enumerate((keys.chunk(B, 10, 0), keys.event(B), keys.stats(B))):
        denied_then_allowed(d.rank_a, key, keys.chunk(A, 10 + i, 0), d.server_seen)
    # and the other way round
    denied_then_allowed(d.rank_b, keys.chunk(A, 20, 1), keys.chunk(B, 20, 1), d.server_seen)


def test_rank_of_a_cannot_hold_a_token_of_b(two_runs):
    d = two_runs
    forged = d.rank_a.liveliness().declare_token(keys.rank_token(B, 7))
    token = d.rank_a.liveliness().declare_token(keys.rank_token(A, 7))  # same link, after it
    own = d.rank_b.liveliness().declare_token(keys.rank_token(B, 8))  # B's rank may
    try:
        assert d.server_tokens.wait_for(keys.rank_token(A, 7))
        assert d.server_tokens.wait_for(keys.rank_token(B, 8))
        assert keys.rank_token(B, 7) not in d.server_tokens.keys
    finally:
        for t in (own, token, forged):
            t.undeclare()


def test_rank_of_a_cannot_read_the_spec_of_b(two_runs):
    d = two_runs
    # get: B's query, then A's on the same link; once A's reply is back, B's query would
    # have reached the server first
    replies_b: list = []
    d.rank_a.get(keys.spec(B), handler=replies_b.append, timeout=TIMEOUT_S)
    queries_b = d.queries[B]
    assert spec_replies(d.rank_a, A) == [f"spec {A}".encode()]
    assert d.queries[B] == queries_b
    assert all(r.ok is None for r in replies_b)
    assert spec_replies(d.rank_b, B) == [f"spec {B}".encode()]  # B's rank may
    # follow: the server puts B's spec then A's (one link); rank A follows both. Once A's has
    # arrived its subscriptions are in place; one more pair, and A's second arrival comes
    # after B's would have
    start = d.rank_a_seen.keys.count(keys.spec(A))
    for _ in range(20):
        d.server.put(keys.spec(B), b"B", congestion_control=zenoh.CongestionControl.BLOCK)
        d.server.put(keys.spec(A), b"A", congestion_control=zenoh.CongestionControl.BLOCK)
        if d.rank_a_seen.wait_count(keys.spec(A), start + 1, TIMEOUT_S / 20):
            break
    seen = d.rank_a_seen.keys.count(keys.spec(A))
    assert seen > start
    d.server.put(keys.spec(B), b"B", congestion_control=zenoh.CongestionControl.BLOCK)
    d.server.put(keys.spec(A), b"A", congestion_control=zenoh.CongestionControl.BLOCK)
    assert d.rank_a_seen.wait_count(keys.spec(A), seen + 1)
    assert keys.spec(B) not in d.rank_a_seen.keys


def test_viewer_of_a_reads_a_only(two_runs):
    d = two_runs
    # the server's frame of B, then of A (one link): the viewer gets A's only
    denied_then_allowed(d.server, keys.frame(B, "side"), keys.frame(A, "side"), d.viewer_a_seen)
    assert not any(k.startswith(f"minority/{B}/") for k in d.viewer_a_seen.keys)
    # it gets A's spec, not B's
    queries_b = d.queries[B]
    d.viewer_a.get(keys.spec(B), handler=lambda r: None, timeout=TIMEOUT_S)
    assert spec_replies(d.viewer_a, A) == [f"spec {A}".encode()]
    assert d.queries[B] == queries_b
    # and puts nothing: its chunk, a round trip through the router, then a rank's chunk
    forged = keys.chunk(A, 30, 9)
    d.viewer_a.put(forged, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
    spec_replies(d.viewer_a, A)
    put_until_seen(d.rank_a, keys.chunk(A, 30, 0), d.server_seen)
    assert forged not in d.server_seen.keys


def closed_on_router(router: zenoh.Session, session: zenoh.Session) -> None:
    """Close `session` and wait until the router has closed its transport: by then the router
    has handled everything `session` sent before."""
    zid, gone = str(session.zid()), threading.Event()
    listener = router.info.declare_transport_events_listener(
        lambda e: e.kind == zenoh.SampleKind.DELETE and str(e.transport.zid) == zid and gone.set())
    try:
        session.close()
        assert gone.wait(TIMEOUT_S) or zid not in [str(t.zid) for t in router.info.transports()]
    finally:
        listener.undeclare()


def test_role_wide_rank_certificate_may_do_nothing(two_runs):
    """make-certs.sh's rank.crt (CN minority-rank) is in no generated rule. Its token, then
    its transport closed at the router, then a token of A's rank: the server sees the last
    only. The same steps with A's rank certificate show that the first token would arrive."""
    d = two_runs
    for config, rank, allowed in ((local_copy("rank.json5", d.certs, d.tmp, A), 40, True),
                                  (local_copy("rank.json5", d.certs, d.tmp), 41, False)):
        session = open_client(config, d.tls)
        try:
            session.liveliness().declare_token(keys.rank_token(A, rank))
        finally:
            closed_on_router(d.router, session)
        marker = d.rank_a.liveliness().declare_token(keys.rank_token(A, 100 + rank))
        assert d.server_tokens.wait_for(keys.rank_token(A, 100 + rank))
        marker.undeclare()
        assert (keys.rank_token(A, rank) in d.server_tokens.keys) is allowed, d.server_tokens.keys


def test_usernames_name_the_run_too(certs, tmp_path):
    router, tls, tcp = open_router(certs, tmp_path, [A, B], loopback_readers=False, usrpwd={
        identity("rank", A): "a-pw", identity("viewer"): "viewer-pw"})
    sessions = [router]
    try:
        def login(user, password):
            session = open_client(local_copy("one-host-client.json5", certs, tmp_path), tcp,
                                  user=(user, password))
            sessions.append(session)
            return session

        reader = login(identity("viewer"), "viewer-pw")  # the role-wide viewer: A and B
        seen = Seen()
        reader.declare_subscriber(keys.everything(B), seen)
        reader.declare_subscriber(keys.everything(A), seen)
        rank = login(identity("rank", A), "a-pw")
        put_until_seen(rank, keys.chunk(A, 1, 0), seen)
        denied_then_allowed(rank, keys.chunk(B, 1, 0), keys.chunk(A, 2, 0), seen)
    finally:
        for session in reversed(sessions):
            session.close()


def test_loopback_readers_read_the_listed_runs(certs, tmp_path):
    """--router's loopback listener (tcp/127.0.0.1, no certificate): read-only."""
    router, tls, tcp = open_router(certs, tmp_path, [A])
    sessions = [router]
    try:
        server = open_client(local_copy("server.json5", certs, tmp_path), tls, Role.SERVER)
        sessions.append(server)
        server.declare_queryable(keys.spec(A), lambda q: q.reply(keys.spec(A), b"spec"))
        reader, intruder = (zenoh.open(make_config(NetworkOptions(connect=[tcp]), Role.CLIENT))
                            for _ in range(2))
        sessions += [reader, intruder]
        seen = Seen()
        reader.declare_subscriber(keys.everything(A), seen)
        rank = open_client(local_copy("rank.json5", certs, tmp_path, A), tls)
        sessions.append(rank)
        put_until_seen(rank, keys.chunk(A, 1, 0), seen)
        forged = keys.chunk(A, 2, 9)
        intruder.put(forged, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
        assert spec_replies(intruder, A) == [b"spec"]  # a round trip: the put was handled
        put_until_seen(rank, keys.chunk(A, 3, 0), seen)
        assert forged not in seen.keys
    finally:
        for session in reversed(sessions):
            session.close()


def test_a_subscription_to_every_run_gets_nothing(two_runs):
    """Per-run rules: `minority/**` is within no run's rules, so the router refuses it; a
    reader subscribes per run (`minority record --run R`). A round trip through the router
    (get the spec) after the subscription and after the server's frame: had the router taken
    the subscription, the frame would come before the second reply (same priority, one link
    from the server and one to the reader). A subscription to run A does get the server's
    frame (waited for, bounded: under load its route may settle after the first reply)."""
    d = two_runs
    for key_expr, frame, allowed in ((keys.everything(), keys.frame(A, "top"), False),
                                     (keys.everything(A), keys.frame(A, "front"), True)):
        viewer = d.open(local_copy("viewer.json5", d.certs, d.tmp))  # role-wide: A and B
        seen = Seen()
        viewer.declare_subscriber(key_expr, seen)
        assert spec_replies(viewer, A) == [f"spec {A}".encode()]
        if allowed:  # the positive control: the frame arrives (bounded wait; routes settle)
            put_until_seen(d.server, frame, seen)
            continue
        d.server.put(frame, b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        assert spec_replies(viewer, A) == [f"spec {A}".encode()]
        assert frame not in seen.keys, (key_expr, seen.keys)


def test_slurm_script_issues_the_runs_certificate_and_rules(tmp_path):
    """minority.sbatch's certificate and config steps, run as written (HEAD = localhost), give
    a router, server and rank that work, the rank with the run's certificate."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl not found")
    script = (DEPLOY / "slurm" / "minority.sbatch").read_text()
    block = script[script.index("# --- certificates"):script.index("# --- stop what")]
    tls_dir = tmp_path / "tls"
    env = {**os.environ, "TLS_DIR": str(tls_dir), "JOB_DIR": str(tmp_path), "RUN": A,
           "HEAD": "localhost", "PY": sys.executable}
    subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=ROOT, env=env, check=True,
                   capture_output=True, timeout=120)
    assert common_name(tls_dir / f"rank.{A}.crt") == identity("rank", A)
    rank_config = (tmp_path / "rank.json5").read_text()
    assert f'"{tls_dir}/rank.{A}.key"' in rank_config and '"deploy/tls' not in rank_config
    cfg = zenoh.Config.from_file(str(tmp_path / "router.json5"))
    assert without_nulls(ac(cfg)) == router_access_control([A])
    port = free_port()
    cfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    sessions = [zenoh.open(cfg)]
    try:
        server = open_client(tmp_path / "server.json5", f"tls/127.0.0.1:{port}", Role.SERVER)
        sessions.append(server)
        seen = Seen()
        server.declare_subscriber(keys.chunks(A), seen)
        rank = open_client(tmp_path / "rank.json5", f"tls/127.0.0.1:{port}")
        sessions.append(rank)
        put_until_seen(rank, keys.chunk(A, 1, 0), seen)
    finally:
        for session in reversed(sessions):
            session.close()


def test_oracle_of_a_updates_a_spec_only(two_runs, tmp_path):
    """The follower's identity: its spec update of A reaches the server and A's rank; its
    update of B (put just before one of A, in order over one link) and a viewer's update of
    A (then a round trip) do not."""
    d = two_runs
    oracle = d.open(local_copy("oracle.json5", d.certs, tmp_path, A))
    watch = Counting()
    for run in (A, B):
        d.server.declare_subscriber(keys.spec(run), watch)
    put_until_seen(oracle, keys.spec(A), watch)
    denied_then_allowed(oracle, keys.spec(B), keys.spec(A), watch)
    assert keys.spec(B) not in watch.keys
    d.viewer_a.put(keys.spec(A), b"viewer's", congestion_control=zenoh.CongestionControl.BLOCK)
    spec_replies(d.viewer_a, A)  # a round trip after the put
    oracle.put(keys.spec(A), b"update", congestion_control=zenoh.CongestionControl.BLOCK)
    assert watch.wait_item(keys.spec(A), b"update")
    assert (keys.spec(A), b"viewer's") not in watch.items  # it would have come first
    assert d.rank_a_seen.wait_for(keys.spec(A))  # the rank of A follows the update
    assert spec_replies(oracle, A) == [f"spec {A}".encode()]  # it gets the spec too

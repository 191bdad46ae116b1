"""The session factory: embedded defaults, the shipped config files, explicit QoS."""

import json
import queue
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port

from minority.protocol.session import (
    ACCEPT_PENDING,
    ACCEPT_TIMEOUT_MS,
    CHUNK_QOS,
    CONTROL_QOS,
    DEFAULT_ENDPOINT,
    LOSSLESS_QOS,
    SHM_POOL_BYTES,
    SHM_POOL_MAX_BYTES,
    SHM_POOL_MIN_BYTES,
    NetworkOptions,
    Role,
    make_config,
    open_session,
    put,
    shm_pool_for,
)

DEPLOY = Path(__file__).parent.parent / "deploy"


def get(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


def test_embedded_server_defaults():
    cfg = make_config(NetworkOptions(), Role.SERVER)
    assert get(cfg, "mode") == "peer"
    assert get(cfg, "listen/endpoints") == [DEFAULT_ENDPOINT]
    assert get(cfg, "scouting/multicast/enabled") is False
    shm = get(cfg, "transport/shared_memory")
    assert shm["enabled"] and shm["transport_optimization"]["pool_size"] == SHM_POOL_BYTES
    assert SHM_POOL_BYTES >= 2 * 1_000_000 * (12 + 4 * 4)  # two 1M-particle chunks with 4 fields
    # unauthenticated connections: bounded in time and number (tests/test_flood.py)
    assert get(cfg, "transport/unicast/accept_timeout") == ACCEPT_TIMEOUT_MS
    assert get(cfg, "transport/unicast/accept_pending") == ACCEPT_PENDING


def test_the_shared_memory_pool_is_sized_for_two_of_the_largest_messages():
    assert shm_pool_for(20_000_000) == 40_000_000
    assert shm_pool_for(1_000) == SHM_POOL_MIN_BYTES
    assert shm_pool_for(10**12) == SHM_POOL_MAX_BYTES
    cfg = make_config(NetworkOptions(shm_pool_bytes=shm_pool_for(20_000_000)), Role.CLIENT)
    assert get(cfg, "transport/shared_memory/transport_optimization/pool_size") == 40_000_000


def test_a_message_larger_than_the_shared_memory_pool_still_arrives_whole():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    client = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5,
                                         shm_pool_bytes=SHM_POOL_MIN_BYTES), Role.CLIENT)
    got: queue.Queue = queue.Queue()
    sub = server.declare_subscriber("test/pool", lambda s: got.put(s.payload.to_bytes()))
    try:
        rng = np.random.default_rng(0)
        for size in (SHM_POOL_MIN_BYTES // 4, 2 * SHM_POOL_MIN_BYTES + 8, SHM_POOL_MIN_BYTES // 4):
            payload = bytearray(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
            put(client, "test/pool", payload, LOSSLESS_QOS)
            assert got.get(timeout=10) == payload  # put stamps the sent time into payload
    finally:
        sub.undeclare()
        client.close()
        server.close()


def test_embedded_client_defaults_and_flags():
    cfg = make_config(NetworkOptions(connect=["tcp/127.0.0.1:9999"]), Role.CLIENT)
    assert get(cfg, "mode") == "client"
    assert get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:9999"]
    assert get(make_config(NetworkOptions(), Role.CLIENT), "connect/endpoints") == [DEFAULT_ENDPOINT]


@pytest.mark.parametrize("name,role", [("zenoh-server.json5", Role.SERVER),
                                       ("zenoh-client.json5", Role.CLIENT)])
def test_shipped_config_files_load(name, role):
    cfg = make_config(NetworkOptions(config=DEPLOY / name), role)
    assert get(cfg, "mode") == ("peer" if role is Role.SERVER else "client")
    assert get(cfg, "scouting/multicast/enabled") is False
    if role is Role.SERVER:  # bounds unauthenticated connections as the embedded default does
        embedded = make_config(NetworkOptions(), Role.SERVER)
        for key in ("accept_timeout", "accept_pending"):
            assert get(cfg, f"transport/unicast/{key}") == get(embedded, f"transport/unicast/{key}")


def test_config_files_with_endpoint_overrides_connect():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(NetworkOptions(config=DEPLOY / "zenoh-server.json5", listen=[endpoint]),
                          Role.SERVER)
    client = open_session(NetworkOptions(config=DEPLOY / "zenoh-client.json5", connect=[endpoint],
                                         connect_timeout_s=5), Role.CLIENT)
    try:
        assert [str(z) for z in client.info.routers_zid() + client.info.peers_zid()] \
            == [str(server.zid())]
    finally:
        client.close()
        server.close()


def test_qos_is_explicit():
    assert CHUNK_QOS.congestion == zenoh.CongestionControl.DROP
    assert CONTROL_QOS.congestion == zenoh.CongestionControl.BLOCK

"""Spec updates put by another peer (an oracle following the run) on minority/{run}/spec:
the render server adopts them (serves, renders and logs the new spec), a publishing rank
follows the same put without stopping, and a malformed update or another run's spec is
refused with the spec kept. Loopback; waits on counts."""

import io

import pytest
from conftest import make_chunk
from test_loopback import wait_until
from test_render_daemon import RUN, spec

from minority.insitu import connect
from minority.protocol import Spec, decode_as, keys
from minority.protocol.log import read_log
from minority.protocol.session import CONTROL_QOS, LOSSLESS_QOS, put


def updated(every_steps: int, reason: str) -> Spec:
    d = spec().to_dict()
    d["views"][0]["schedule"] = [{"every_steps": every_steps}]
    d["provenance"] = {"reason": reason, "forecast_s": 1.5}
    return Spec.from_dict(d)


@pytest.fixture
def daemon(render_server_of):
    return render_server_of(spec())


def test_the_server_and_a_rank_follow_a_spec_put_by_another_peer(daemon, client_factory,
                                                                   endpoint, tmp_path):
    follower = client_factory()
    viz = connect(RUN, connect=(endpoint,), wait_s=5.0, log=io.StringIO(), report=False)
    try:
        assert viz.spec == spec() and viz.due(0, 0.0) and not viz.due(1, 1e-3)
        new = updated(2, "the flow started 0.1 s early")
        put(follower, keys.spec(RUN), new.encode(), CONTROL_QOS)
        assert wait_until(lambda: daemon.spec_updates == 1 and viz.spec == new)
        assert daemon.spec == new and daemon.spec.provenance["reason"].startswith("the flow")
        answer = follower.get(keys.spec(RUN), timeout=5.0)
        served = [decode_as(r.ok.payload.to_bytes(), Spec) for r in answer if r.ok]
        assert served == [new]
        assert viz.due(2, 2e-3) and not viz.due(3, 3e-3)  # the rank's schedule: every 2nd
        # a step sent under the new spec renders with it (every 2nd step is due)
        chunk = make_chunk(n=40, step=2, rank=0, ranks=1, run=RUN)
        put(follower, keys.chunk(RUN, 2, 0), chunk.encode(), LOSSLESS_QOS)
        assert wait_until(lambda: daemon.stats.frames == 1)
    finally:
        viz.close()
    daemon.close()
    specs = [r.decode() for r in read_log(tmp_path / "run.mcap") if r.topic == f"minority/{RUN}/spec"]
    assert specs == [spec(), new] and specs[1].provenance["forecast_s"] == 1.5
    assert daemon.summary()["spec_updates"] == 1


@pytest.mark.parametrize(("payload", "problem"), [
    (b"{not json", "refused a spec update"),
    (None, "its run is 'another-run'"),
])
def test_a_bad_spec_update_is_refused_and_the_spec_kept(daemon, client_factory, payload,
                                                        problem):
    if payload is None:
        d = updated(2, "x").to_dict()
        d["run"] = "another-run"
        payload = bytes(Spec.from_dict(d).encode())
    follower = client_factory()
    follower.put(keys.spec(RUN), payload)  # as given: not stamped
    assert wait_until(lambda: daemon.spec_updates_refused == 1)
    assert daemon.spec == spec() and daemon.spec_updates == 0
    assert problem in daemon.stats.last_error
    assert daemon.summary()["spec_updates_refused"] == 1


def test_replay_renders_each_step_with_the_spec_in_force_when_it_was_logged(
        daemon, client_factory, tmp_path):
    """Step 20 under the first spec (every 20th step), then an update to every 3rd step,
    then step 21: the server renders both; the replay of its log with the log's specs too
    (with the last spec alone, step 20 would not be due)."""
    from minority.cli import main

    follower = client_factory()
    for step, frames in ((20, 1), (21, 2)):
        if step == 21:
            put(follower, keys.spec(RUN), updated(3, "late").encode(), CONTROL_QOS)
            assert wait_until(lambda: daemon.spec_updates == 1)
        chunk = make_chunk(n=40, step=step, rank=0, ranks=1, run=RUN)
        put(follower, keys.chunk(RUN, step, 0), chunk.encode(), LOSSLESS_QOS)
        assert wait_until(lambda n=frames: daemon.stats.frames == n)
    daemon.close()
    live = sorted(p.name for p in (tmp_path / "frames").rglob("*.png"))
    assert live == ["000020.png", "000021.png"]
    assert main(["replay", str(tmp_path / "run.mcap"), "--out", str(tmp_path / "re"), "-q"]) == 0
    replayed = sorted((tmp_path / "re").rglob("*.png"))
    assert [p.name for p in replayed] == live
    for p in replayed:
        assert p.read_bytes() == (tmp_path / "frames" / RUN / "side" / p.name).read_bytes()

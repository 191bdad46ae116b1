"""deploy/slurm/minority.sbatch run end to end on this host, as Slurm would run it.

Slurm is stood in for by the small executables of tests/slurm_shims/ on PATH: `scontrol
show hostnames` (the allocation: localhost, localhost, 127.0.0.1, so the first node and
both rank "nodes" are this machine, the rank nodes under two names), `srun` (a job step:
N tasks as N MPI ranks under the .venv's mpiexec; Hydra's proxies, when Hydra's
`-bootstrap slurm` starts them, as given) and `zenohd` (a router opened with eclipse-zenoh
from the job's router.json5: its TLS listener and access control). The script makes the
certificates and configs, starts the router, the render server (one process, or a job step
of 2 render ranks) and the 2 sim ranks of the 400-particle `tiny` scene over mutual TLS,
then stops the server and the router. Checked what a user would check: exit status 0,
frames on disk, the MCAP log (and its shard) with the run's start, chunks of both sim ranks
and its end, the router's rules naming the run, the router certificate naming the first
node.

Loopback only (free ports, TLS_PORT/LOCAL_PORT), no multicast (the configs turn scouting
off), every wait bounded (the job, JOB_TIMEOUT_S). Not covered: a real Slurm (its srun,
its PMI plugins, several hosts)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from conftest import TINY_SPEC, free_port

from minority.protocol import EventKind
from minority.protocol.log import read_log

ROOT = Path(__file__).parent.parent
SCRIPT = ROOT / "deploy" / "slurm" / "minority.sbatch"
SHIMS = Path(__file__).parent / "slurm_shims"
RUN = "tiny"
JOB_TIMEOUT_S = 300  # the script with the server's start (its kernels may compile) and the sim
SPEC = TINY_SPEC

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found")


def job_env(tmp: Path, **settings: str) -> dict[str, str]:
    """What sbatch gives the script on a 3-node allocation (1 task per node), plus the
    script's settings: the tiny scene, SPEC, 2 sim ranks, free loopback ports."""
    spec = tmp / "spec.json"
    spec.write_text(json.dumps(SPEC))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "PMI_", "PMIX_"))}
    env.update({
        "PATH": f"{SHIMS}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{env['PATH']}",
        "SLURM_NNODES": "3", "SLURM_JOB_NODELIST": "localhost,localhost,127.0.0.1",
        "SLURM_NTASKS_PER_NODE": "1", "SLURM_JOB_ID": "4242", "SLURM_SUBMIT_DIR": str(ROOT),
        "JOB_DIR": str(tmp / "job"), "SCENE": "tiny", "SPEC": str(spec), "RANKS": "2",
        "TLS_PORT": str(free_port()), "LOCAL_PORT": str(free_port()),
        "SRUN_SHIM_LOG": str(tmp / "srun-calls.jsonl"),
    })
    env.update(settings)
    return env


def run_script(env: dict[str, str], cwd: Path = ROOT) -> tuple[int, str]:
    """`bash minority.sbatch` (from `cwd`, in a session of its own), its exit status and
    output; stopped (SIGTERM, then SIGKILL) past JOB_TIMEOUT_S or as soon as serve.log shows
    a traceback, so a crashed server fails the test at once."""
    out = Path(env["JOB_DIR"] + ".out")
    out.parent.mkdir(parents=True, exist_ok=True)
    serve_log = Path(env["JOB_DIR"]) / "serve.log"
    with out.open("w") as sink:
        proc = subprocess.Popen(["bash", str(SCRIPT)], cwd=cwd, env=env, stdout=sink,
                                stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + JOB_TIMEOUT_S
    try:
        while True:
            try:
                rc = proc.wait(timeout=1.0)
                break
            except subprocess.TimeoutExpired:
                crashed = serve_log.exists() and "Traceback" in serve_log.read_text()
                if crashed or time.monotonic() > deadline:
                    why = "minority serve crashed" if crashed else "the job timed out"
                    pytest.fail(f"{why}:\n{out.read_text()[-2000:]}\nserve.log:\n"
                                f"{serve_log.read_text()[-3000:] if serve_log.exists() else ''}")
    finally:
        if proc.poll() is None:  # the script's trap stops the server and the router
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return rc, out.read_text()


def srun_calls(env: dict[str, str]) -> list[list[str]]:
    path = Path(env["SRUN_SHIM_LOG"])
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def check_job(env: dict[str, str], rc: int, output: str, serve_ranks: int) -> None:
    job = Path(env["JOB_DIR"])
    logs = "".join(f"\n{p.name}:\n{p.read_text()[-2000:]}" for p in sorted(job.glob("*.log")))
    assert rc == 0, output[-3000:] + logs
    assert "sim exited with status 0" in output
    # the server rendered the last step and exited by itself (not stopped past DRAIN_S)
    assert "every rank is done and the last step rendered" in (job / "serve.log").read_text()
    # the router certificate names the first node, the host every client connects to
    san = subprocess.run(["openssl", "x509", "-in", str(job / "tls" / "router.crt"), "-noout",
                          "-ext", "subjectAltName"], capture_output=True, text=True,
                         check=True, timeout=30).stdout
    assert "DNS:localhost" in san
    # the router ran this job's config: its ports, access control for this run only
    assert f"tls/0.0.0.0:{env['TLS_PORT']}" in (job / "zenohd.log").read_text()
    acl = json.loads(zenoh.Config.from_file(str(job / "router.json5")).get_json("access_control"))
    names = {n for s in acl["subjects"] for n in s.get("cert_common_names") or []}
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert f"minority-rank.{RUN}" in names and "minority-rank" not in names
    assert all(k.startswith(f"minority/{RUN}/") for r in acl["rules"] for k in r.get("key_exprs") or [])
    # frames, and the log: the server's and the sim's start, chunks of both sim ranks, the end
    assert list((job / "frames" / RUN).glob("*/*.png"))
    shard = job / "frames" / f"{RUN}.render1.mcap"
    assert shard.exists() == (serve_ranks > 1)
    events, chunk_ranks = [], set()
    for record in read_log(str(job / "frames" / f"{RUN}.mcap")):
        message = record.decode()
        if record.topic.endswith("/event"):
            events.append((message.kind, message.rank))
        elif "/chunk" in record.topic:
            chunk_ranks.add(message.rank)
    assert (EventKind.RUN_START, -1) in events and (EventKind.RUN_START, 0) in events
    assert events[-1][0] == EventKind.RUN_END
    assert chunk_ranks == {0, 1}


def test_one_server_process_ranks_under_srun(tmp_path):
    """The default path (SERVE_RANKS=1): one `minority serve`, the sim as an srun step."""
    env = job_env(tmp_path, LAUNCHER="srun")
    rc, output = run_script(env)
    check_job(env, rc, output, serve_ranks=1)
    calls = srun_calls(env)  # one step: the 2 sim ranks on the rank nodes
    assert len(calls) == 1 and "--ntasks=2" in calls[0] and "--relative=1" in calls[0]


@pytest.mark.slow  # 20-90 s each on the 2 shared cores: 2 render ranks start, then the sim
@pytest.mark.parametrize("launcher", ["srun", "mpiexec"])
def test_render_ranks_as_a_job_step(tmp_path, launcher):
    """SERVE_RANKS=2: the server as a job step of 2 render ranks, then the sim ranks; started
    by srun, or by Hydra's mpiexec whose `-bootstrap slurm` starts its proxies with srun."""
    env = job_env(tmp_path, LAUNCHER=launcher, SERVE_RANKS="2")
    rc, output = run_script(env)
    check_job(env, rc, output, serve_ranks=2)
    calls = srun_calls(env)
    proxies = [c for c in calls if any(Path(a).name == "hydra_pmi_proxy" for a in c)]
    if launcher == "srun":
        assert len(calls) == 2 and not proxies
        assert "--ntasks=2" in calls[0] and "--relative=0" in calls[0]  # the render ranks
    else:
        assert len(proxies) == len(calls) == 2  # one Hydra launch a step
        # the sim's: one proxy on each rank node (each reads its id from SLURM_NODEID)
        assert calls[1][calls[1].index("--nodelist") + 1] == "localhost,127.0.0.1"
        assert calls[1][calls[1].index("-n") + 1] == "2"


@pytest.mark.parametrize("settings, message", [
    ({"SLURM_NNODES": "1"}, "needs at least 2 nodes"),
    ({"LAUNCHER": "ssh"}, "LAUNCHER must be mpiexec or srun"),
    ({"ZENOHD": "no-such-zenohd"}, "no-such-zenohd not found"),
    ({"SERVE_RANKS": "two"}, "SERVE_RANKS must be a positive whole number, not 'two'"),
    ({"RANKS": "0"}, "RANKS must be a positive whole number"),
])
def test_refuses_what_cannot_run(tmp_path, settings, message):
    env = job_env(tmp_path, **settings)
    rc, output = run_script(env)
    assert rc == 1 and message in output, output
    assert not (tmp_path / "job").exists()  # refused before it made anything


def test_must_be_submitted_from_the_repository(tmp_path):
    env = job_env(tmp_path, SLURM_SUBMIT_DIR=str(tmp_path))
    rc, output = run_script(env, cwd=tmp_path)
    assert rc == 1 and "submit from the repository root" in output


def test_a_server_that_does_not_start_fails_the_job(tmp_path):
    """A server that exits before it serves: the script says so, exits 1, and stops the
    router it started (its trap)."""
    env = job_env(tmp_path, SERVE_ARGS="--no-such-flag")
    rc, output = run_script(env)
    assert rc == 1 and "minority serve exited, see" in output, output
    assert "--no-such-flag" in (tmp_path / "job" / "serve.log").read_text()
    assert "stopped" in (tmp_path / "job" / "zenohd.log").read_text()

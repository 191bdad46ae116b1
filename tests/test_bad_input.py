"""Hostile and damaged input gives one clear line naming the problem, never a traceback:
spec files and SPEC messages, scenes asking for terabytes, GNS checkpoints that are not
checkpoints, and truncated or damaged MCAP logs (read up to their last complete chunk, and
said so). Exit status 2 for bad input, 0 when a truncated log still gave its output."""

from __future__ import annotations

import json
import math
import pickle
import warnings

import numpy as np
import pytest
import torch
from conftest import make_chunk

from minority.cli import main
from minority.protocol import Spec, Stats, Timing
from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.log import LogDamagedWarning, LogTruncatedWarning, LogWriter
from minority.protocol.messages import SPEED_BINS, decode_as, decode_message, speed_histogram
from minority.protocol.spec import MAX_INT_DIGITS, MAX_SPEC_FILE_BYTES
from minority.protocol.wire import FORMAT_VERSION, MAGIC, PREFIX, PREFIX_SIZE, MessageKind
from minority.sim.scene import (
    GRID_BYTES_PER_CELL,
    MAX_GRID_CELLS,
    MAX_PARTICLES,
    PARTICLE_BYTES,
    SCENES_DIR,
    SceneError,
    loads_scene,
)

RUN = "bad-input"
SHIPPED_CHECKPOINT = SCENES_DIR.parent.parent / "gns" / "checkpoints" / "column_l64_m5.pt"
DEEP = 100_000  # nesting levels of the deep JSON documents


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of `minority ARGV` in this process; a log warning that
    escapes the command (instead of being said on one line) fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogTruncatedWarning)
        warnings.simplefilter("error", LogDamagedWarning)
        status = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return status, out, err


def spec_dict() -> dict:
    return {"version": 2, "run": RUN,
            "views": [{"name": "side", "width": 32, "height": 24, "field": "displacement",
                       "camera": {"position": [0.5, -2.0, 0.2], "focal_point": [0.5, 0.25, 0.1]},
                       "schedule": [{"every_steps": 20}]}]}


# --- 1. spec files and SPEC messages -----------------------------------------------------
BAD_SPEC_FILES = {
    "invalid_utf8": (b'{"version": 2, "run": "\xff\xfe"}', "not UTF-8 text (byte 0xff at offset 23)"),
    "huge_integer": (b'{"version": ' + b"9" * 5000 + b', "run": "x", "views": []}',
                     f"a 5000-digit integer (at most {MAX_INT_DIGITS} digits"),
    "deep_nesting": (b"[" * DEEP + b"]" * DEEP, "JSON nested too deeply"),
    "nan": (b'{"version": 2, "run": "x", "views": [], "provenance": {"a": NaN}}', "holds NaN"),
    "overflowing_float": (b'{"version": 2, "run": "x", "views": [], "provenance": {"a": 1e999}}',
                          "holds the number 1e999, beyond the range of a 64-bit float"),
}


@pytest.mark.parametrize("name", list(BAD_SPEC_FILES))
def test_bad_spec_file_is_a_spec_error(tmp_path, name):
    data, message = BAD_SPEC_FILES[name]
    path = tmp_path / f"{name}.json"
    path.write_bytes(data)
    with pytest.raises(SpecError, match=f"^{path}: ") as caught:
        Spec.load(path)
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_oversized_spec_file_is_refused_before_parsing(tmp_path):
    path = tmp_path / "big.json"
    path.write_bytes(b" " * (MAX_SPEC_FILE_BYTES + 1))
    with pytest.raises(SpecError, match="MAX_SPEC_FILE_BYTES"):
        Spec.load(path)


def test_a_spec_file_that_loads_can_be_sent(tmp_path):
    d = spec_dict()
    d["provenance"] = {"seed": 2**63 - 1, "nested": json.loads("[" * 500 + "]" * 500)}
    (tmp_path / "s.json").write_text(json.dumps(d))
    spec = Spec.load(tmp_path / "s.json")
    assert decode_as(spec.encode(), Spec) == spec


@pytest.mark.parametrize("name", ["invalid_utf8", "huge_integer", "deep_nesting"])
def test_bad_spec_file_on_the_command_line(tmp_path, capsys, name):
    data, message = BAD_SPEC_FILES[name]
    spec = tmp_path / "spec.json"
    spec.write_bytes(data)
    log = tmp_path / "run.mcap"
    with LogWriter(log) as w:
        w.write(make_chunk(run=RUN, step=0))
    for argv in (["report", "score", str(spec), str(log)],
                 ["replay", str(log), "--spec", str(spec), "--out", str(tmp_path / "r")]):
        status, _, err = run_cli(capsys, argv)
        assert status == 2 and message in err and str(spec) in err
        assert len(err.strip().splitlines()) == 1, err
    # serve refuses the spec before opening a session (its status is minority/cli.py's)
    status, _, err = run_cli(capsys, ["serve", "--spec", str(spec), "--no-record"])
    assert status != 0 and err.startswith("minority serve: error: ") and message in err


def raw_spec_message(header: bytes) -> bytes:
    """A SPEC payload with this header JSON as it came off the wire (no encoder checks)."""
    out = bytearray(PREFIX_SIZE + len(header))
    PREFIX.pack_into(out, 0, MAGIC, FORMAT_VERSION, int(MessageKind.SPEC), 0, len(header), 0,
                     len(out), 0)
    out[PREFIX_SIZE:] = header
    return bytes(out)


@pytest.mark.parametrize("meta, message", [
    (b'{"version":2,"run":"\xff\xfe","views":[]}', "not valid JSON: Invalid UTF-8"),
    (b'{"version":' + b"9" * 5000 + b',"run":"x","views":[]}', "out of range"),
    (b'{"version":2,"run":"x","views":' + b"[" * DEEP + b"]" * DEEP + b"}",
     "maximum recursion depth"),
])
def test_bad_spec_message_is_a_protocol_error(meta, message):
    payload = raw_spec_message(b'{"meta":' + meta + b',"arrays":[]}')
    for decode in (decode_message, lambda p: decode_as(p, Spec)):
        with pytest.raises(ProtocolError, match=message):
            decode(payload)


# --- 2. scenes that ask for more memory than a process should allocate -------------------
TINY = (SCENES_DIR / "tiny.toml").read_text()


def test_a_grid_past_the_limit_is_refused_before_allocating():
    assert "cell_size_m = 0.02\n" in TINY
    with pytest.raises(SceneError) as caught:
        loads_scene(TINY.replace("cell_size_m = 0.02\n", "cell_size_m = 1e-5\n"))
    text = str(caught.value)
    assert "40,000 x 4,000 x 16,000 = 2,560,000,000,000 cells (164 TB at 64 bytes per cell)" in text
    assert f"limit of {MAX_GRID_CELLS:,} cells (MAX_GRID_CELLS" in text
    smallest_m = float(text.split("cell size of at least ")[1].split(" m")[0])  # the fix
    assert math.prod(s / smallest_m for s in (0.4, 0.04, 0.16)) <= MAX_GRID_CELLS
    with pytest.raises(SceneError, match="more than 1e308"):  # size / cell size is infinite
        loads_scene(TINY.replace("cell_size_m = 0.02\n", "cell_size_m = 5e-324\n"))


def test_too_many_particles_are_refused_before_seeding():
    text = (TINY.replace("cell_size_m = 0.02\n", "cell_size_m = 0.002\n")
            .replace("per_cell_per_axis = 2 ", "per_cell_per_axis = 8 "))
    with pytest.raises(SceneError, match=f"about 25,600,000 particles .* limit of "
                                         f"{MAX_PARTICLES:,} particles \\(MAX_PARTICLES"):
        loads_scene(text)


def test_the_memory_estimates_are_what_the_sim_allocates():
    from minority.sim.state import make_grid, seed_particles

    scene = loads_scene(TINY)
    grid = make_grid(scene)
    assert grid.data.nbytes == GRID_BYTES_PER_CELL * math.prod(grid.data.shape[:3])
    particles = seed_particles(scene)
    arrays = [getattr(particles, f) for f in ("x", "v", "C", "F", "tau", "mass", "vol0", "x0",
                                              "pid")]
    assert sum(a.nbytes for a in arrays) == PARTICLE_BYTES * particles.n


def test_sim_of_a_huge_grid_says_so(tmp_path, capsys):
    scene = tmp_path / "huge.toml"
    scene.write_text(TINY.replace("cell_size_m = 0.02\n", "cell_size_m = 1e-5\n"))
    status, _, err = run_cli(capsys, ["sim", str(scene), "--no-publish", "--quiet",
                                      "--out", str(tmp_path / "huge.h5")])
    # a scene error's status is minority/cli.py's
    assert status != 0 and err.startswith("minority sim: error: ") and "MAX_GRID_CELLS" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "huge.h5").exists()


# --- 3. and 5. truncated and damaged logs ------------------------------------------------
def write_flushed_log(path, messages) -> bytes:
    """Each message in its own MCAP chunk, the file left without its footer (a killed
    writer); returns the bytes written."""
    w = LogWriter(path, overwrite=True)
    for ns, message in enumerate(messages, start=1):
        w.write(message, log_ns=ns)
        w.flush()
    w.abandon()
    return path.read_bytes()


def write_cut_log(path, messages) -> None:
    """The flushed log of `messages` cut in the middle of the chunk of the last one."""
    before = len(write_flushed_log(path, messages[:-1]))
    data = write_flushed_log(path, messages)
    path.write_bytes(data[:(before + len(data)) // 2])


def stats_messages(steps: int) -> list[Stats]:
    """Stats of a run at rest (no displacement yet), as at the start of a run."""
    hist = speed_histogram(np.zeros(10))
    return [Stats(RUN, 0, k, 0.01 * k, 10, 0.0, 0.0, 0.0, True, hist, [0] * SPEED_BINS)
            for k in range(steps)]


def test_score_of_a_truncated_log(tmp_path, capsys):
    spec = tmp_path / "spec.json"
    Spec.from_dict(spec_dict()).save(spec)
    log = tmp_path / "run.mcap"
    write_cut_log(log, stats_messages(6))
    status, out, err = run_cli(capsys, ["report", "score", str(spec), str(log),
                                        "--out", str(tmp_path / "s")])
    assert status == 0
    assert err.startswith(f"minority report score: warning: log truncated: {log}: ")
    assert "complete chunks" in err and len(err.strip().splitlines()) == 1
    assert "**Log truncated**" in out and out == (tmp_path / "s" / "score.md").read_text()
    result = json.loads((tmp_path / "s" / "score.json").read_text())
    assert result["log"]["complete"] is False and result["log"]["notes"][0]["kind"] == "truncated"
    assert result["stats_steps"] == 5  # the sixth was in the cut chunk
    assert result["displacement_max_m"]["actual"] == 0.0
    assert result["displacement_max_m"]["relative_error"] is None  # not a division by zero


def report_log(path, damage: str = "truncated", timings: bool = True):
    """A run of 4 steps (a spec, 2 chunks and a timing each) in flushed chunks, without its
    footer and "truncated" (cut inside its last chunk) or "damaged" (a byte inverted in the
    middle of the MCAP chunk of step 20's first chunk, so step 0 and its timing come before)."""
    spec = Spec.from_dict(spec_dict())
    messages = [spec]
    for step in (0, 20, 40, 60):
        messages += [make_chunk(n=40, step=step, rank=r, run=RUN, seed=step + r) for r in (0, 1)]
        if timings:
            messages.append(Timing(RUN, step, "side", step * 1e-4, 0.01, 0.002, 0.003, 5000,
                                   80, 2, 2, False))
    if damage == "truncated":
        write_cut_log(path, messages)
    else:
        before, through = (len(write_flushed_log(path, messages[:k])) for k in (4, 5))
        data = bytearray(write_flushed_log(path, messages))
        data[(before + through) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("damage", ["truncated", "damaged"])
def test_report_of_a_truncated_or_damaged_log(tmp_path, capsys, damage):
    log = report_log(tmp_path / "run.mcap", damage)
    status, out, err = run_cli(capsys, ["report", str(log), "--out", str(tmp_path / "plots")])
    assert status == 0 and out.startswith(f"# minority report: run `{RUN}`")
    assert err.startswith(f"minority report: warning: log {damage}: {log}: ")
    assert len(err.strip().splitlines()) == 1
    assert f"**Log {damage}**: {log}: " in out  # the report itself says so
    rendered = int(out.split("- rendered steps: ")[1].split("\n")[0])
    assert rendered == (3 if damage == "truncated" else 1)  # the timing of step 60 was cut
    assert (tmp_path / "plots" / "run.timing.png").is_file()


def test_replay_of_a_truncated_log(tmp_path, capsys):
    log = report_log(tmp_path / "run.mcap", timings=False)  # cut in rank 1's chunk of step 60
    status, out, err = run_cli(capsys, ["replay", str(log), "--out", str(tmp_path / "frames"),
                                        "--quiet"])
    assert status == 0 and out.startswith(f"run {RUN}: 4 steps replayed")
    assert "1 incomplete steps (step: chunks of ranks): 60: 1/2" in out
    assert err.startswith(f"minority replay: warning: log truncated: {log}: ")
    assert "complete chunks" in err and len(err.strip().splitlines()) == 1
    assert f"log truncated: {log}: " in out
    assert sorted(p.name for p in (tmp_path / "frames" / "side").iterdir()) == [
        "000000.png", "000020.png", "000040.png", "000060.png"]


def test_replay_of_a_log_cut_before_its_first_chunk(tmp_path, capsys):
    log = report_log(tmp_path / "run.mcap")
    log.write_bytes(log.read_bytes()[:40])
    status, _, err = run_cli(capsys, ["replay", str(log), "--out", str(tmp_path / "f")])
    lines = err.strip().splitlines()
    assert status == 2 and lines[0].startswith("minority replay: warning: log truncated")
    assert lines[1].startswith("minority replay: error: ") and len(lines) == 2


# --- 4. files that are not GNS checkpoints -----------------------------------------------
class RunsCode:
    """A pickle that calls print("PWNED") when unpickled without weights_only."""

    def __reduce__(self):
        return print, ("PWNED",)


def bad_checkpoints(tmp_path) -> dict:
    files = {"empty.pt": b"", "garbage.pt": np.random.default_rng(0).bytes(4096),
             "plain.pkl": pickle.dumps({"format": "minority-gns-checkpoint/1"}, protocol=4),
             "code.pkl": pickle.dumps(RunsCode(), protocol=2),
             "cut.pt": SHIPPED_CHECKPOINT.read_bytes()[:100_000]}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    torch.save([1, 2, 3], tmp_path / "list.pt")
    torch.save({"format": "minority-gns-checkpoint/1"}, tmp_path / "keys.pt")
    return {"empty.pt": "empty file", "garbage.pt": "not a PyTorch checkpoint",
            "plain.pkl": "refused by the weights-only loader",
            "code.pkl": "Unsupported global: GLOBAL print",
            "cut.pt": "not a readable PyTorch checkpoint", "list.pt": "holds a list",
            "keys.pt": "checkpoint lacks model_config, stats, state_dict"}


def test_oracle_refuses_what_is_not_a_checkpoint(tmp_path, capsys):
    for name, message in bad_checkpoints(tmp_path).items():
        path = tmp_path / name
        for step, argv in (("ship", ["ship", str(path), "-o", str(tmp_path / "shipped.pt")]),
                           ("rollout", ["rollout", str(path), "tiny",
                                        "--out", str(tmp_path / "rollout")])):
            status, out, err = run_cli(capsys, ["oracle", *argv])
            assert status == 2, (name, step, err)
            assert err.startswith(f"minority oracle {step}: error: {path}: ") and message in err
            assert "expected a minority-gns-checkpoint/1 file" in err
            assert len(err.strip().splitlines()) == 1 and "PWNED" not in out
            assert not (tmp_path / "shipped.pt").exists() and not (tmp_path / "rollout").exists()


def test_checkpoint_whose_weights_do_not_fit_its_config(tmp_path, capsys):
    ckpt = torch.load(SHIPPED_CHECKPOINT, weights_only=True)
    ckpt["model_config"] = {**ckpt["model_config"], "latent": ckpt["model_config"]["latent"] // 2}
    torch.save(ckpt, tmp_path / "mismatch.pt")
    status, _, err = run_cli(capsys, ["oracle", "ship", str(tmp_path / "mismatch.pt"),
                                      "-o", str(tmp_path / "shipped.pt")])
    assert status == 2 and "size mismatch" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "shipped.pt").exists()

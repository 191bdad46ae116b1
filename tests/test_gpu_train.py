"""deploy/gpu/train.sh, the one command that trains the reference GNS on a GPU machine, run
here on the CPU with its tiny configuration (TINY=1: 4 short scenes, a small model, a few
seconds of training): dataset, a time-boxed training with checkpoints, the test split's
scores."""

import json
import os
import subprocess
import sys
from pathlib import Path

from minority.gns.train import load_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def test_the_gpu_training_command_runs_end_to_end_on_a_tiny_configuration(tmp_path):
    out = tmp_path / "gpu"
    env = {**os.environ, "TINY": "1", "OUT": str(out), "PYTHON": sys.executable, "JOBS": "2",
           "TRAIN_S": "4", "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run(["sh", str(ROOT / "deploy" / "gpu" / "train.sh")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    log = (out / "train.log").read_text()
    assert "stopped at step" in log and "(--max-wall-s)" in log  # the time box, not --steps
    model, ckpt = load_checkpoint(out / "gns_l128_m10.best.pt")
    assert ckpt["model_config"]["latent"] == 16 and ckpt["train_config"]["max_wall_s"] == 4.0
    scores = json.loads((out / "eval.json").read_text())
    assert [s["scene"] for s in scores["scenes"]] == ["test_000"]
    assert all(s["relative_error"]["runout"] >= 0 for s in scores["scenes"])

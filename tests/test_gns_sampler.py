"""Training windows: where in a run they are drawn (gns.train.Sampler)."""

import numpy as np
import pytest

from minority.gns.dataset import Trajectory
from minority.gns.events import find_events
from minority.gns.train import Sampler

C, DT = 5, 0.005  # input velocities, frame interval (s)


def slump(frames=120, moving=30, n=8):
    """A run that moves for `moving` frames and then rests, with a drift of 1e-9 m per frame
    in y that makes every frame unique: [frames, n, 3] m."""
    k = np.arange(frames, dtype=np.float64)
    x = 0.02 * np.minimum(k, moving) - 0.01 * np.minimum(k, moving) ** 2 / moving
    pos = np.zeros((frames, n, 3))
    pos[:, :, 0] = x[:, None] + np.arange(n) * 0.01
    pos[:, :, 1] = 1e-9 * k[:, None]
    return Trajectory("slump", pos.astype(np.float64), 30.0, np.array([[0, 2.0]] * 3))


def last_frames(sampler, traj, draws=300):
    return [int(round(w[0][0, -1, 1] / 1e-9)) for w in
            (sampler.window(0.015) for _ in range(draws))]


def test_moving_windows_end_before_the_scene_is_at_rest():
    traj = slump()
    rest = C + 1 + round(find_events(traj.positions, DT).runout_end_s / DT)
    assert 30 < rest < 45  # at rest from about frame 30, plus the C frames that see it stop
    everywhere = last_frames(Sampler([traj], C, 0.0, np.random.default_rng(0)), traj)
    assert max(everywhere) > 100 and min(everywhere) >= C
    moving = last_frames(Sampler([traj], C, 0.0, np.random.default_rng(0), 1.0, DT), traj)
    assert min(moving) >= C and max(moving) < rest
    half = last_frames(Sampler([traj], C, 0.0, np.random.default_rng(0), 0.5, DT), traj)
    share = np.mean(np.array(half) < rest)
    assert 0.5 < share < 0.75  # half always, plus the other half's share of moving frames


def test_moving_fraction_outside_zero_to_one_is_refused(tmp_path):
    from minority.gns.model import ModelConfig
    from minority.gns.train import TrainConfig, train

    with pytest.raises(ValueError, match="moving_fraction 1.5"):
        train(tmp_path / "missing", tmp_path / "m.pt", ModelConfig(),
              TrainConfig(moving_fraction=1.5), device="cpu")

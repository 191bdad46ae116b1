"""Training: random-walk noise on the input velocities, optional pushforward windows
(gns.pushforward), normalized acceleration loss, exponential learning-rate decay, validation
rollouts, checkpoints with resume.

A checkpoint is a dict of tensors and plain values (loads with `weights_only=True`):
format, model_config, stats (normalization, radius, frame interval, bounds), state_dict,
optimizer (absent in a shipped checkpoint), step, train_config, history. With an exponential
moving average of the weights (`ema_decay` > 0), state_dict holds the averaged weights (what
validation, rollout and evaluation use) and train_state_dict the optimizer's (for resume).
"""

from __future__ import annotations

import math
import pickle
import sys
import time
import warnings
import zipfile
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from minority.gns.dataset import load_metadata, load_split
from minority.gns.events import find_events
from minority.gns.graph import radius_graph
from minority.gns.model import GNS, ModelConfig, deepen
from minority.gns.pushforward import draw_steps, unroll

CHECKPOINT_FORMAT = "minority-gns-checkpoint/1"
STAT_KEYS = ("vel_mean", "vel_std", "acc_mean", "acc_std", "friction_mean_deg",
             "friction_std_deg", "connectivity_radius_m", "frame_interval_s", "bounds_m",
             "particle_spacing_m", "input_velocities")


@dataclass
class TrainConfig:
    steps: int = 100_000
    batch: int = 2  # trajectory windows per step (disjoint graphs)
    lr: float = 1e-3
    lr_final: float = 1e-5
    lr_decay_steps: int = 100_000  # lr = lr_final + (lr - lr_final) * 0.1 ** (step / this)
    noise_std: float = 3e-5  # m/frame, std of the input velocity noise at the last frame
    val_every: int = 2_000  # steps between validation rollouts
    val_frames: int = 100  # rollout length of a validation rollout
    ckpt_every: int = 500
    keep_validated: bool = False  # also keep a copy OUT_step<N>.pt at every validation
    ema_decay: float = 0.0  # > 0: validate and save an exponential moving average of weights
    pushforward_steps: int = 0  # > 0: windows unrolled 1..this many frames (gns.pushforward)
    pushforward_prob: float = 0.5  # the fraction of windows unrolled
    moving_fraction: float = 0.0  # > 0: this fraction of windows ends while its scene moves
    seed: int = 0
    max_wall_s: float | None = None  # stop after this many s of training (then validate, save)


def coarse_grain_stats(meta: dict) -> dict:
    """How the dataset was coarse-grained from the MPM (older datasets: factor 1, "mean")."""
    return {"coarse_grain": int(meta.get("coarse_grain", 1)),
            "coarse_grain_method": str(meta.get("coarse_grain_method", "mean"))}


def combined_stats(meta: dict, noise_std: float) -> dict:
    """Metadata statistics with the noise folded into the stds (as learning_to_simulate)."""
    stats = {k: meta[k] for k in STAT_KEYS}
    stats.update(coarse_grain_stats(meta))  # how the MPM data were made
    for key in ("vel_std", "acc_std"):
        stats[key] = [math.sqrt(s * s + noise_std * noise_std) for s in meta[key]]
    return stats


CHECKPOINT_KEYS = ("format", "model_config", "stats", "state_dict")  # what every one holds
ZIP_MAGIC = b"PK\x03\x04"  # torch.save's format: a zip archive
PICKLE_MAGIC = b"\x80"  # the legacy torch.save format and plain pickles: the PROTO opcode


class CheckpointError(ValueError):
    """A file is not a readable GNS checkpoint; the message names the file and what is wrong."""


TORCH_APPEALS = (" (Could this error message be improved?", " This is an internal miniz error")


def _gist(exc: BaseException, limit: int = 200) -> str:
    """A torch or pickle error on one line, without PyTorch's appeals, at most `limit` chars."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    for appeal in TORCH_APPEALS:
        text = text.split(appeal)[0]
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _unpickler_reason(exc: pickle.UnpicklingError) -> str:
    """What torch's weights-only unpickler refused, e.g. 'Unsupported global: GLOBAL print
    was not an allowed global by default'."""
    after = str(exc).partition("WeightsUnpickler error:")[2].strip().splitlines()
    return after[0].split(". Please")[0].strip()[:120] if after else _gist(exc)


def read_checkpoint(path: str | Path, device: str = "cpu") -> dict:
    """The checkpoint dict at `path`, loaded with `weights_only=True` (tensors and plain
    values only: a pickle of other objects is refused, never run) and checked to hold
    CHECKPOINT_KEYS; CheckpointError otherwise (OSError when the file cannot be read)."""
    expected = f"expected a {CHECKPOINT_FORMAT} file from `minority oracle train`"
    with open(path, "rb") as f:  # a missing file stays an OSError (the CLI's status 1)
        head = f.read(len(ZIP_MAGIC))
    if not head:
        raise CheckpointError(f"{path}: empty file; {expected}")
    try:
        with warnings.catch_warnings():  # torch warns of pickle protocols it did not write
            warnings.simplefilter("ignore", UserWarning)
            ckpt = torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as exc:
        if not head.startswith((ZIP_MAGIC, PICKLE_MAGIC)):
            raise CheckpointError(f"{path}: not a PyTorch checkpoint (it starts with bytes "
                                  f"{head.hex(' ')}); {expected}") from None
        raise CheckpointError(f"{path}: refused by the weights-only loader "
                              f"({_unpickler_reason(exc)}): a pickle of more than tensors and "
                              f"plain values, or not written by torch.save; nothing in it was "
                              f"run; {expected}") from None
    except (EOFError, RuntimeError, ValueError, zipfile.BadZipFile, UnicodeDecodeError,
            KeyError, TypeError, AttributeError, IndexError) as exc:
        raise CheckpointError(f"{path}: not a readable PyTorch checkpoint "
                              f"({type(exc).__name__}: {_gist(exc)}); {expected}") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path}: holds a {type(ckpt).__name__}, not a checkpoint dict; "
                              f"{expected}")
    if ckpt.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: format {str(ckpt.get('format'))[:60]!r}, not "
                              f"{CHECKPOINT_FORMAT!r}; {expected}")
    missing = [k for k in CHECKPOINT_KEYS if k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}; {expected}")
    return ckpt


def load_checkpoint(path: str | Path, device: str = "cpu") -> tuple[GNS, dict]:
    """(model in eval mode, checkpoint dict); CheckpointError when the file is not a
    checkpoint or its weights do not fit its model config."""
    ckpt = read_checkpoint(path, device)
    config, names = ckpt["model_config"], {f.name for f in fields(ModelConfig)}
    if (not isinstance(config, dict) or not set(config) <= names
            or not all(type(v) is int and v >= 0 for v in config.values())):
        raise CheckpointError(f"{path}: model_config {str(config)[:120]} is not a set of "
                              f"non-negative integers among {sorted(names)}")
    try:
        model = GNS(ModelConfig(**config), ckpt["stats"]).to(device)
        model.load_state_dict(ckpt["state_dict"])
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(f"{path}: its weights and statistics do not make its model "
                              f"({type(exc).__name__}: {_gist(exc)})") from None
    return model.eval(), ckpt


def ship(src: str | Path, dst: str | Path) -> Path:
    """Copy a checkpoint without its optimizer state (what the repository ships); only one
    whose weights make its model (load_checkpoint) is copied."""
    _, ckpt = load_checkpoint(src)
    ckpt.pop("optimizer", None)
    ckpt.pop("train_state_dict", None)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, dst)
    return dst


class Sampler:
    """Random training windows: C+1 input frames and the next frame, with noise."""

    def __init__(self, trajs, c: int, noise_std: float, rng: np.random.Generator,
                 moving_fraction: float = 0.0, frame_interval_s: float = 1.0) -> None:
        self.trajs, self.c, self.noise, self.rng = trajs, c, noise_std, rng
        self.weights = np.array([t.positions.shape[0] - c - 1 for t in trajs], np.float64)
        self.weights /= self.weights.sum()
        # a scene moves until its kinetic energy is back at rest (gns.events), plus C frames
        # so that windows see it stop; most frames of a 1 s run are at rest otherwise
        self.moving_fraction = moving_fraction
        self.rest_frame = [min(t.positions.shape[0] - 1, c + 1 + round(
            find_events(t.positions, frame_interval_s).runout_end_s / frame_interval_s))
            for t in trajs] if moving_fraction > 0 else []

    def window(self, radius: float, steps: int = 0, advance=None):
        """steps > 0: a pushforward window; the noisy inputs end `steps` frames earlier and
        advance(inputs [n, C+1, 3], friction_deg, bounds_m, steps) (gns.pushforward.unroll
        with the model) predicts the frames up to the last input frame. As with the noise,
        the target keeps the true velocity of the last step: the loss asks the model to
        cancel its velocity drift in one frame (a target of the true position gave losses
        100 times the plain ones)."""
        i = self.rng.choice(len(self.trajs), p=self.weights)
        t, u = self.trajs[i], steps
        end = t.positions.shape[0] - 1
        if self.moving_fraction > 0 and self.rng.random() < self.moving_fraction:
            end = max(self.c + u + 1, min(end, self.rest_frame[i]))
        k = int(self.rng.integers(self.c + u, end))  # last input frame
        pos = t.positions[k - self.c - u:k + 2].astype(np.float64)  # [C+u+2, n, 3]
        n = pos.shape[1]
        vel_noise = self.rng.normal(0.0, self.noise / math.sqrt(self.c), (self.c, n, 3))
        pos_noise = np.concatenate([np.zeros((1, n, 3)), np.cumsum(np.cumsum(
            vel_noise, axis=0), axis=0)])  # random walk: none on the oldest frame
        inputs = np.transpose(pos[:self.c + 1] + pos_noise, (1, 0, 2))  # [n, C+1, 3]
        if u == 0:
            target = pos[-1] + pos_noise[-1]  # keep the true velocity of the last step
        else:
            inputs = advance(inputs, t.friction_angle_deg, t.bounds_m, u)
            target = inputs[:, -1] + pos[-1] - pos[-2]
        senders, receivers = radius_graph(inputs[:, -1], radius)
        return inputs, target, np.full(n, t.friction_angle_deg), t.bounds_m, senders, receivers


def _batch(windows, device):
    pos, tgt, fr, _b, s, r, bounds = [], [], [], [], [], [], []
    off = 0
    for inputs, target, friction, bnd, snd, rcv in windows:
        pos.append(inputs)
        tgt.append(target)
        fr.append(friction)
        bounds.append(np.broadcast_to(bnd, (len(friction), 3, 2)))
        s.append(snd + off)
        r.append(rcv + off)
        off += len(friction)
    t = lambda a, dt=torch.float32: torch.as_tensor(np.concatenate(a), dtype=dt, device=device)  # noqa: E731
    return t(pos), t(tgt), t(fr), t(bounds), t(s, torch.int64), t(r, torch.int64)


def train(dataset: str | Path, out: str | Path, model_config: ModelConfig, cfg: TrainConfig, *,
          resume: str | Path | None = None, init: str | Path | None = None,
          deepen_to: int | None = None, device: str | None = None, log=None) -> Path:
    """Train; write out (the latest checkpoint) and out with suffix .best.pt (best val).

    resume: continue a run (weights, optimizer, step, history). init: start from a
    checkpoint's weights, model config and statistics, with a fresh optimizer and schedule
    (fine-tuning, e.g. with another noise level); the statistics stay the checkpoint's so
    that the weights keep their meaning. deepen_to (with init): append identity
    message-passing steps up to this many (gns.model.deepen).
    """
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    if resume and init:
        raise ValueError("resume and init are exclusive: give one")
    if deepen_to is not None and not init:
        raise ValueError("deepen_to needs init (the checkpoint to deepen)")
    if not 0 <= cfg.moving_fraction <= 1:
        raise ValueError(f"moving_fraction {cfg.moving_fraction} must be within [0, 1]")
    from minority.gns.rollout import rollout_error
    from minority.gns.runtime import tune_allocator

    tune_allocator()
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    meta = load_metadata(dataset)
    train_trajs, val_trajs = load_split(dataset, "train"), load_split(dataset, "valid")
    step, history, ckpt = 0, [], {}
    if resume or init:
        model, ckpt = load_checkpoint(resume or init, device)  # its config and statistics win
        stats, model_config = ckpt["stats"], model.config
    if resume:
        step, history = int(ckpt["step"]), list(ckpt.get("history", []))
    elif init:
        history = [{"init": str(init), "init_step": int(ckpt["step"])}]
        ckpt = {}  # fresh optimizer
        for key in ("particle_spacing_m", "frame_interval_s", "connectivity_radius_m"):
            if not math.isclose(float(stats[key]), float(meta[key]), rel_tol=1e-6):
                raise ValueError(f"init: the checkpoint's {key} {stats[key]} is not the "
                                 f"dataset's {meta[key]}")
        stats = {**stats, **coarse_grain_stats(meta)}  # the data's
        if deepen_to is not None:
            history[0]["deepened_from"] = model.config.message_passing
            model = deepen(model, stats, deepen_to)
            model_config = model.config
    else:
        stats = combined_stats(meta, cfg.noise_std)
        model = GNS(model_config, stats).to(device)
    if cfg.pushforward_steps < 0 or not 0 <= cfg.pushforward_prob <= 1:
        raise ValueError(f"pushforward: steps {cfg.pushforward_steps} must be >= 0 and the "
                         f"probability {cfg.pushforward_prob} within [0, 1]")
    ema = None
    if cfg.ema_decay > 0:  # starts from the loaded weights (the average, when resuming one)
        if not cfg.ema_decay < 1:
            raise ValueError(f"ema_decay {cfg.ema_decay} must be below 1")
        ema = torch.optim.swa_utils.AveragedModel(
            model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(cfg.ema_decay))
    if resume and "train_state_dict" in ckpt:
        model.load_state_dict(ckpt["train_state_dict"])
        if ema is not None:
            ema.n_averaged.fill_(1)  # keep the resumed average, do not restart it
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    if "optimizer" in ckpt:
        opt.load_state_dict(ckpt["optimizer"])
    if resume or init:
        print(f"train: {'resumed' if resume else 'initialized from'} {resume or init} "
              f"at step {step}", file=log, flush=True)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(cfg.seed + step)
    sampler = Sampler(train_trajs, model_config.input_velocities, cfg.noise_std, rng,
                      cfg.moving_fraction, float(meta["frame_interval_s"]))

    def advance(inputs, friction_deg, bounds_m, steps):  # the weights being trained
        return unroll(model, inputs, friction_deg, bounds_m, steps, device)

    acc_mean = torch.as_tensor(stats["acc_mean"], device=device)
    acc_std = torch.as_tensor(stats["acc_std"], device=device)
    best = min((h["val_error_m"] for h in history if h.get("val_complete")), default=math.inf)
    n_params = sum(p.numel() for p in model.parameters())
    print(f"train: {len(train_trajs)} train / {len(val_trajs)} valid scenes, model "
          f"{asdict(model_config)} ({n_params} parameters), {device}, "
          f"{torch.get_num_threads()} threads", file=log, flush=True)

    def evaluated() -> GNS:  # the weights validated and saved as state_dict
        return model if ema is None else ema.module

    def save(path: Path) -> None:
        extra = {"train_state_dict": model.state_dict()} if ema is not None else {}
        torch.save({"format": CHECKPOINT_FORMAT, "model_config": model_config.to_dict(),
                    "stats": stats, "state_dict": evaluated().state_dict(),
                    "optimizer": opt.state_dict(), "step": step, "train_config": asdict(cfg),
                    "history": history, **extra}, path.with_suffix(".tmp"))
        path.with_suffix(".tmp").replace(path)

    t0, t_last, loss_acc, n_acc = time.perf_counter(), time.perf_counter(), 0.0, 0
    model.train()
    while step < cfg.steps:
        lr = cfg.lr_final + (cfg.lr - cfg.lr_final) * 0.1 ** (step / cfg.lr_decay_steps)
        for g in opt.param_groups:
            g["lr"] = lr
        pos, tgt, fr, bounds, s, r = _batch(
            [sampler.window(model.radius, draw_steps(rng, cfg.pushforward_steps,
                                                     cfg.pushforward_prob), advance)
             for _ in range(cfg.batch)], device)
        last, prev = pos[:, -1], pos[:, -2]
        acc_target = ((tgt - 2 * last + prev) - acc_mean) / acc_std
        pred = model(pos, fr, bounds, s, r)
        loss = ((pred - acc_target) ** 2).sum(dim=1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if ema is not None:
            ema.update_parameters(model)
        step += 1
        loss_acc += loss.detach().item()
        n_acc += 1
        now = time.perf_counter()
        last = step == cfg.steps or (cfg.max_wall_s is not None and now - t0 >= cfg.max_wall_s)
        if now - t_last > 10 or last:
            rate = n_acc / max(now - t_last, 1e-9)
            print(f"train: step {step}/{cfg.steps} loss {loss_acc / n_acc:.4f} lr {lr:.2e} "
                  f"{rate:.2f} steps/s", file=log, flush=True)
            history.append({"step": step, "loss": loss_acc / n_acc, "lr": lr,
                            "wall_s": now - t0})
            t_last, loss_acc, n_acc = now, 0.0, 0
        if step % cfg.ckpt_every == 0 or last:
            save(out)
        if val_trajs and (step % cfg.val_every == 0 or last):
            model.eval()
            scores = [rollout_error(evaluated().eval(), t, cfg.val_frames, device)
                      for t in val_trajs]
            model.train()
            err = float(np.mean([sc["error_m"] for sc in scores]))
            reached = min(sc["frames"] for sc in scores)
            want = min(cfg.val_frames, min(t.positions.shape[0] for t in val_trajs)
                       - model_config.input_velocities - 1)
            entry = {"step": step, "val_error_m": err, "val_frames": reached,
                     "val_complete": reached >= want}
            deposit_note = ""
            if all(sc["runout"] is not None for sc in scores):  # full-length rollouts
                for key in ("runout", "displacement_range"):
                    entry[f"val_{key}_error_max"] = max(sc[key] for sc in scores)
                # a checkpoint tends to overrun (or stop short) on every scene at once
                entry["val_runout_signed"] = [sc["runout_signed"] for sc in scores]
                entry["val_height_signed"] = [sc["height_signed"] for sc in scores]
                bias = float(np.mean(entry["val_runout_signed"]))
                flat = float(np.mean(np.abs(entry["val_height_signed"])))
                deposit_note = (f", worst scene runout {100 * entry['val_runout_error_max']:.1f}"
                                f" %, displacement range "
                                f"{100 * entry['val_displacement_range_error_max']:.1f} %, "
                                f"mean signed runout error {100 * bias:+.1f} %, mean final "
                                f"height error {100 * flat:.1f} %")
            history.append(entry)
            print(f"train: step {step} validation rollout mean position error {err:.5f} m"
                  + deposit_note
                  + ("" if reached >= want else f" (a rollout diverged at frame {reached})"),
                  file=log, flush=True)
            if cfg.keep_validated:
                save(out.with_name(f"{out.stem}_step{step}.pt"))
            if reached >= want and err < best:
                best = err
                save(out.with_suffix(".best.pt"))
        if last and step < cfg.steps:
            print(f"train: stopped at step {step} after {now - t0:.0f} s (--max-wall-s)",
                  file=log, flush=True)
            break
    save(out)
    return out


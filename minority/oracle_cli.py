"""`minority oracle STEP`: the GNS surrogate's steps, each a parser builder beside its handler
(`_dataset_parser`, `_cmd_dataset`, ...), in pipeline order in `STEPS`. Conventions (-o/--out,
defaults in --help, exit statuses) in minority/cliargs.py."""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

from minority.cliargs import BAD_INPUT, FAILED, add_out, command, fail, missing, parent_made

# package data of minority.gns, found where the package is installed (a wheel's site-packages,
# or the source tree); installed as files, never zipped, so each is a plain path
GNS_DATA = Path(str(resources.files("minority.gns")))
DEFAULT_SWEEP = GNS_DATA / "configs" / "column_sweep.toml"
DEFAULT_CHECKPOINT = GNS_DATA / "checkpoints" / "column_l64_m5.pt"


def _fail(step: str, exc: Exception, status: int) -> int:
    return fail(f"oracle {step}", exc, status)


def _load_for_cpu(args: argparse.Namespace):
    """(model, checkpoint) of args.checkpoint, with the CPU allocator tuned and
    args.threads torch threads (raises CheckpointError or OSError as load_checkpoint)."""
    import torch

    from minority.gns.runtime import tune_allocator
    from minority.gns.train import load_checkpoint

    tune_allocator()
    if args.threads:
        torch.set_num_threads(args.threads)
    return load_checkpoint(args.checkpoint)


def _checkpoint_on_scenes_args(q: argparse.ArgumentParser) -> None:
    """CHECKPOINT DATASET [--split] [--scene ...] [--threads], as evaluate and diagnose take them."""
    q.add_argument("checkpoint", type=Path, help="checkpoint from minority oracle train")
    q.add_argument("dataset", type=Path, help="dataset directory (minority oracle dataset)")
    q.add_argument("--split", default="test", choices=["train", "valid", "test"],
                   help="the dataset's split to run on")
    q.add_argument("--scene", action="append", help="only this scene (repeatable; default: all)")
    q.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")


# --- dataset ----------------------------------------------------------------------------

def _existing(text: str) -> Path:
    """An input file that must exist (a usage error, exit status 2, when it does not)."""
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return Path(text)


def _existing_path(text: str) -> Path:
    """An input file or directory that must exist (a usage error, exit status 2, if not)."""
    if not Path(text).exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file or directory")
    return Path(text)


def _dataset_parser(osub) -> None:
    q = command(osub, "dataset", help="build the dataset: our MPM sweep, any simulator's runs, "
                                      "or a geoelements/gns npz dataset",
                description="By default: plan column-collapse scenes from the config's ranges "
                            "(train / valid / test by scene, held-out aspect ratios and "
                            "friction angles in test), run each with `minority sim` (finished "
                            "runs are kept and skipped), pack the dataset. --from-runs packs "
                            "HDF5 runs of any simulator instead (layout: gns/README.md, "
                            "'Runs of any simulator'); --from-npz converts a dataset of "
                            "geoelements/gns (train.npz, valid.npz, test.npz, metadata.json).")
    q.add_argument("--config", type=_existing,
                   help="sweep config TOML (default: the shipped gns/configs/column_sweep.toml)")
    q.add_argument("--runs", type=Path, default=Path("data/sweep"), metavar="DIR",
                   help="where the MPM runs go")
    add_out(q, "dataset directory", default=Path("data/dataset"), metavar="DIR")
    q.add_argument("--extra-train", type=int, metavar="N", help="N more train scenes than the "
                   "config's split, drawn after its test scenes: every scene of the config "
                   "and its run stay (default: the config's extra_train, else 0)")
    q.add_argument("--extra-valid", type=int, metavar="N",
                   help="the same for validation scenes (default: the config's extra_valid, "
                        "else 0)")
    q.add_argument("--jobs", type=int, default=1, help="sims run at once")
    q.add_argument("--threads", type=int, default=1, help="numba threads per sim")
    src = q.add_mutually_exclusive_group()
    src.add_argument("--from-runs", type=_existing_path, action="append", metavar="PATH",
                     help="pack these runs instead of the sweep: an .h5 file or a folder of "
                          "them (repeatable); a folder's train/, valid/, test/ subfolders "
                          "give their splits, other files are split by --valid / --test")
    src.add_argument("--from-npz", type=_existing_path, metavar="DIR",
                     help="convert this geoelements/gns dataset instead of the sweep (or an "
                          "export-npz directory of domain_NN datasets)")
    q.add_argument("--valid", type=int, default=1, metavar="N",
                   help="--from-runs: the last N runs by file name (before the test ones) "
                        "validate")
    q.add_argument("--test", type=int, default=0, metavar="N",
                   help="--from-runs: the last N runs by file name are the test split")
    q.add_argument("--stride", type=int, default=1, metavar="K",
                   help="--from-runs: keep every K-th frame (the model's frame interval is K "
                        "frame intervals of the runs)")
    q.add_argument("--radius", type=float, metavar="M",
                   help="--from-runs, --from-npz: connectivity radius, m (default: 1.81 "
                        "particle spacings, as the shipped model; --from-npz: the radius its "
                        "metadata.json gives)")
    q.add_argument("--friction-deg", type=float, metavar="DEG",
                   help="--from-runs, --from-npz: friction angle of runs that carry no "
                        "material (without it such a run is refused)")
    q.add_argument("--material", choices=["tan_phi", "deg", "none"], default="tan_phi",
                   help="--from-npz: what a trajectory's material_property holds: tan of the "
                        "friction angle (their ColumnCollapseFrictional data), degrees, or "
                        "nothing to use")
    q.add_argument("--frame-interval", type=float, metavar="S",
                   help="--from-npz: s between frames (default: the metadata's dt)")
    q.set_defaults(func=_cmd_dataset)


def _cmd_dataset(args: argparse.Namespace) -> int:
    from minority.gns.dataset import DatasetError, build
    from minority.gns.sweep import SweepError, load_config
    from minority.sweep import run_sweep

    try:
        if args.from_runs or args.from_npz:
            meta = _dataset_from_files(args)
        else:
            args.config = args.config or DEFAULT_SWEEP
            cfg = load_config(args.config)
            for key in ("extra_train", "extra_valid"):
                if getattr(args, key) is not None:
                    cfg.splits = {**cfg.splits, key: getattr(args, key)}
            runs = run_sweep(cfg, args.runs, jobs=args.jobs, threads=args.threads)
            meta = build(runs, args.out, stride=cfg.stride,
                         connectivity_radius_m=cfg.connectivity_radius_m,
                         config_path=str(args.config), coarse_grain=cfg.coarse_grain,
                         coarse_grain_method=cfg.coarse_grain_method)
    except (SweepError, DatasetError, OSError) as exc:
        return _fail("dataset", exc, FAILED)
    except ValueError as exc:  # a run or npz file that is not in its layout
        return _fail("dataset", exc, BAD_INPUT)
    counts = {s: sum(sc["split"] == s for sc in meta["scenes"]) for s in ("train", "valid", "test")}
    print(f"dataset {args.out}: {counts}, frame interval {meta['frame_interval_s']} s, "
          f"radius {meta['connectivity_radius_m']} m", file=sys.stderr)
    return 0


def _dataset_from_files(args: argparse.Namespace) -> dict:
    """The dataset of --from-runs or --from-npz. Raises ValueError (bad input: checked before
    anything is written) or DatasetError / OSError."""
    from minority.gns.dataset import DatasetError
    from minority.gns.from_runs import build_from_runs, collect
    from minority.gns.npz import NpzError, import_npz

    try:
        if args.from_npz:
            return import_npz(args.from_npz, args.out, material=args.material,
                              frame_interval_s=args.frame_interval,
                              friction_deg=args.friction_deg,
                              connectivity_radius_m=args.radius)
        if args.valid < 0 or args.test < 0:
            raise ValueError(f"--valid {args.valid} and --test {args.test} must be >= 0")
        collect(args.from_runs, args.valid, args.test)  # the splits, before any file is read
        return build_from_runs(args.from_runs, args.out, stride=args.stride, valid=args.valid,
                               test=args.test, connectivity_radius_m=args.radius,
                               friction_deg=args.friction_deg)
    except (NpzError, DatasetError) as exc:  # bad input, not a failure at run time
        raise ValueError(str(exc)) from None


# --- export-npz -------------------------------------------------------------------------

def _export_npz_parser(osub) -> None:
    q = command(osub, "export-npz", help="write a dataset in the npz layout of geoelements/gns",
                description="Write DATASET as geoelements/gns reads one: train.npz, valid.npz, "
                            "test.npz (per trajectory: positions [T, n, 3] m, particle_type "
                            "[n], the friction angle as their material_property) and "
                            "metadata.json (bounds, sequence_length, "
                            "default_connectivity_radius, dim, dt, velocity and acceleration "
                            "statistics, plus a 'minority' section that `minority oracle "
                            "dataset --from-npz` reads back). sequence_length is the frame "
                            "count (null where lengths differ); scenes with different bounds "
                            "go to one dataset per domain (DIR/domain_NN), or to train and "
                            "rollout sections when only the test split's domain differs.")
    q.add_argument("dataset", type=Path, help="dataset directory (minority oracle dataset)")
    add_out(q, "directory of the npz dataset", metavar="DIR", required=True)
    q.add_argument("--material", choices=["tan_phi", "deg", "none"], default="tan_phi",
                   help="the friction angle as tan(phi) (their ColumnCollapseFrictional "
                        "data), in degrees, or not written")
    q.set_defaults(func=_cmd_export_npz)


def _cmd_export_npz(args: argparse.Namespace) -> int:
    from minority.gns.dataset import DatasetError
    from minority.gns.npz import export_npz

    if (status := missing("oracle export-npz", args.dataset)) is not None:
        return status
    try:
        meta = export_npz(args.dataset, args.out, material=args.material)
    except DatasetError as exc:
        return _fail("export-npz", exc, BAD_INPUT)
    except OSError as exc:
        return _fail("export-npz", exc, FAILED)
    n = sum(len(v) for v in meta["minority"]["scenes"].values())
    print(f"npz dataset {args.out}: {n} trajectories, dt {meta['dt']} s, radius "
          f"{meta['default_connectivity_radius']} m", file=sys.stderr)
    if len(meta["datasets"]) > 1:
        print("one gns dataset per domain: "
              + ", ".join(str(args.out / d) for d in meta["datasets"]), file=sys.stderr)
    return 0


# --- train ------------------------------------------------------------------------------

def _train_parser(osub) -> None:
    q = command(osub, "train", help="train the GNS on a dataset",
                description="Train with random-walk input noise and a normalized acceleration "
                            "loss; writes OUT every --ckpt-every steps and OUT with suffix "
                            ".best.pt at the best validation rollout. Uses a GPU when present.")
    q.add_argument("dataset", type=Path, help="dataset directory (minority oracle dataset)")
    add_out(q, "checkpoint file", default=Path("data/gns.pt"), metavar="OUT.pt")
    q.add_argument("--resume", type=Path, help="continue from this checkpoint (its model "
                                               "config and statistics win)")
    q.add_argument("--init", type=Path, help="fine-tune: start from this checkpoint's weights, "
                                             "model config and statistics with a fresh "
                                             "optimizer and learning-rate schedule")
    q.add_argument("--deepen", type=int, metavar="M",
                   help="with --init: append message-passing steps up to M, each an identity "
                        "at first, so training starts from the checkpoint's predictions and "
                        "can widen its receptive field (M x the connectivity radius)")
    q.add_argument("--latent", type=int, default=128, help="latent size")
    q.add_argument("--mlp-layers", type=int, default=2, help="hidden layers per MLP")
    q.add_argument("--message-passing", type=int, default=10, metavar="M",
                   help="message-passing steps")
    q.add_argument("--steps", type=int, default=100_000, help="total training steps")
    q.add_argument("--batch", type=int, default=2, help="windows per step")
    q.add_argument("--lr", type=float, default=1e-3, help="initial learning rate")
    q.add_argument("--lr-final", type=float, default=1e-5, help="learning-rate floor")
    q.add_argument("--lr-decay-steps", type=int, default=100_000,
                   help="steps per tenfold learning-rate decay")
    q.add_argument("--noise-std", type=float, default=3e-5, metavar="M_PER_FRAME",
                   help="input velocity noise std, m/frame")
    q.add_argument("--val-every", type=int, default=2000, help="steps between validations")
    q.add_argument("--val-frames", type=int, default=100, help="frames per validation rollout")
    q.add_argument("--ckpt-every", type=int, default=500, help="steps between checkpoints")
    q.add_argument("--keep-validated", action="store_true",
                   help="also keep OUT_step<N>.pt at every validation, to choose a checkpoint "
                        "afterwards by the logged runout and displacement-range errors")
    q.add_argument("--ema-decay", type=float, default=0.0, metavar="D",
                   help="validate and save an exponential moving average of the weights, "
                        "updated every step with this decay (e.g. 0.999: about the last "
                        "1,000 steps); 0: the weights as trained")
    q.add_argument("--pushforward", type=int, default=0, metavar="K",
                   help="pushforward training: a window first rolls 1 to K frames forward "
                        "with the model (no gradient) and then learns the true next "
                        "velocity from its own predictions; 0: off")
    q.add_argument("--pushforward-prob", type=float, default=0.5, metavar="P",
                   help="fraction of windows unrolled when --pushforward is on")
    q.add_argument("--moving-fraction", type=float, default=0.0, metavar="F",
                   help="fraction of windows that end while their scene still moves (before "
                        "its kinetic energy is back at rest, gns.events); the rest are drawn "
                        "from the whole run. 0: every frame alike")
    q.add_argument("--seed", type=int, default=0, help="random seed")
    q.add_argument("--max-wall-s", type=float, metavar="S",
                   help="stop after S seconds of training, with a last validation and "
                        "checkpoint (a time-boxed machine; default: run all --steps)")
    q.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    q.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    q.set_defaults(func=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    import torch

    from minority.gns.model import ModelConfig
    from minority.gns.train import TrainConfig, train

    if (status := missing("oracle train", args.dataset, args.resume, args.init)) is not None:
        return status
    if args.resume and args.init:
        return _fail("train", "give --resume or --init, not both", BAD_INPUT)
    if args.deepen is not None and not args.init:
        return _fail("train", "--deepen needs --init (the checkpoint to deepen)", BAD_INPUT)
    if args.threads:
        torch.set_num_threads(args.threads)
    mc = ModelConfig(latent=args.latent, mlp_layers=args.mlp_layers,
                     message_passing=args.message_passing)
    tc = TrainConfig(steps=args.steps, batch=args.batch, lr=args.lr, lr_final=args.lr_final,
                     lr_decay_steps=args.lr_decay_steps, noise_std=args.noise_std,
                     val_every=args.val_every, val_frames=args.val_frames,
                     ckpt_every=args.ckpt_every, keep_validated=args.keep_validated,
                     ema_decay=args.ema_decay, pushforward_steps=args.pushforward,
                     pushforward_prob=args.pushforward_prob,
                     moving_fraction=args.moving_fraction, seed=args.seed,
                     max_wall_s=args.max_wall_s)
    try:
        out = train(args.dataset, args.out, mc, tc, resume=args.resume, init=args.init,
                    deepen_to=args.deepen, device=args.device)
    except ValueError as exc:  # CheckpointError, DatasetError, a bad option
        return _fail("train", exc, BAD_INPUT)
    except OSError as exc:
        return _fail("train", exc, FAILED)
    print(f"checkpoint {out}", file=sys.stderr)
    return 0


# --- evaluate, diagnose -----------------------------------------------------------------

def _evaluate_parser(osub) -> None:
    q = command(osub, "evaluate", help="score a checkpoint on held-out scenes",
                description="Roll out every scene of a split from its first MPM frames and "
                            "compare with the MPM: runout, final height, displacement range "
                            "(relative errors), mean position error (m), rollout time (s). A "
                            "coarse-grained dataset's scenes are also scored against their MPM "
                            "runs at the runs' own resolution (relative_error_full). JSON to "
                            "stdout or --out; exit status 1 when a rollout diverges.")
    _checkpoint_on_scenes_args(q)
    add_out(q, "JSON file (default: stdout)", metavar="FILE.json")
    q.set_defaults(func=_cmd_evaluate)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from minority.gns.evaluate import evaluate

    if (status := missing("oracle evaluate", args.checkpoint, args.dataset)) is not None:
        return status
    try:
        model, ckpt = _load_for_cpu(args)
        rows = evaluate(model, args.dataset, args.split, names=args.scene or None)
    except (ValueError, KeyError) as exc:  # CheckpointError, DatasetError, no such scene
        return _fail("evaluate", exc, BAD_INPUT)
    except OSError as exc:
        return _fail("evaluate", exc, FAILED)
    doc = {"checkpoint": str(args.checkpoint), "step": ckpt["step"],
           "model_config": ckpt["model_config"], "split": args.split, "scenes": rows}
    text = json.dumps(doc, indent=1)
    if args.out:
        try:
            parent_made(args.out).write_text(text)
        except OSError as exc:
            return _fail("evaluate", exc, FAILED)
    else:
        print(text)
    return 0 if all("error" not in r for r in rows) else FAILED


def _bands(text: str) -> list[tuple[int, int]]:
    try:
        bands = [tuple(int(v) for v in part.split(":")) for part in text.split(",")]
    except ValueError:
        bands = []
    if not bands or any(len(b) != 2 for b in bands):
        raise argparse.ArgumentTypeError(f"{text!r}: expected F0:F1[,F0:F1...] (frames)")
    return bands


def _diagnose_parser(osub) -> None:
    q = command(osub, "diagnose", help="one-frame predictions against a run, by region",
                description="Teacher-forced acceleration balance (gns/diagnose.py): each frame "
                            "of a band gets the run's own last frames as input; the predicted "
                            "and the run's x accelerations (m/frame^2) are summed over regions "
                            "of the column (depth below the surface, distance to the side "
                            "walls, front) and the band. A ratio away from 1 shows where and "
                            "when the model adds or removes momentum the run does not. One "
                            "JSON line per (scene, band, region) to stdout, a table to stderr.")
    _checkpoint_on_scenes_args(q)
    q.add_argument("--bands", type=_bands, default="6:10,10:26,26:46,46:80",
                   help="frame bands F0:F1 (last input frames F0..F1-1; frames of the "
                        "dataset's interval, 0.005 s for the shipped data)")
    q.set_defaults(func=_cmd_diagnose)


def _cmd_diagnose(args: argparse.Namespace) -> int:
    import json

    from minority.gns.dataset import load_split
    from minority.gns.diagnose import balance

    if (status := missing("oracle diagnose", args.checkpoint, args.dataset)) is not None:
        return status
    try:
        model, _ = _load_for_cpu(args)
        trajs = [t for t in load_split(args.dataset, args.split)
                 if not args.scene or t.name in args.scene]
        if not trajs:
            raise ValueError(f"no scene {args.scene} in the {args.split} split")
        for traj in trajs:
            for row in balance(model, traj, args.bands):
                print(json.dumps(row), flush=True)
                ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}"
                print(f"diagnose: {row['scene']} frames {row['frames'][0]}-"
                      f"{row['frames'][1] - 1} {row['region']:>22s}: predicted "
                      f"{row['pred_m']:+.2e} run {row['true_m']:+.2e} ratio {ratio}",
                      file=sys.stderr, flush=True)
    except (ValueError, KeyError) as exc:  # CheckpointError, DatasetError, no such scene
        return _fail("diagnose", exc, BAD_INPUT)
    except OSError as exc:
        return _fail("diagnose", exc, FAILED)
    return 0


# --- ship -------------------------------------------------------------------------------

def _ship_parser(osub) -> None:
    q = command(osub, "ship", help="copy a checkpoint without its optimizer state",
                description="Write the checkpoint the repository ships: weights, model config, "
                            "statistics, history; no optimizer state.")
    q.add_argument("checkpoint", type=Path, help="checkpoint from minority oracle train")
    add_out(q, "the shipped checkpoint", metavar="OUT.pt", required=True)
    q.set_defaults(func=_cmd_ship)


def _cmd_ship(args: argparse.Namespace) -> int:
    from minority.gns.train import CheckpointError, ship

    if (status := missing("oracle ship", args.checkpoint)) is not None:
        return status
    try:
        out = ship(args.checkpoint, args.out)
    except CheckpointError as exc:
        return _fail("ship", exc, BAD_INPUT)
    except (OSError, ValueError, RuntimeError) as exc:
        return _fail("ship", exc, FAILED)
    print(f"{out}: {out.stat().st_size / 1e6:.2f} MB", file=sys.stderr)
    return 0


# --- rollout ----------------------------------------------------------------------------

def _rollout_parser(osub) -> None:
    q = command(osub, "rollout", help="predict a scene with a checkpoint",
                description="Seed the scene's bodies at the model's particle spacing (any "
                            "scene resolution), predict its duration frame by frame, write "
                            "DIR/rollout.h5 (positions m, velocities m/s per frame) and "
                            "DIR/vtk/rollout.pvd with one .vtp per frame (displacement and "
                            "velocity arrays) for ParaView. Exit status 1 when the rollout "
                            "diverges.")
    q.add_argument("checkpoint", type=Path, help="checkpoint from minority oracle train")
    q.add_argument("scene", help="scene TOML file or shipped scene name (e.g. column_13k)")
    add_out(q, "output directory", default=Path("rollout"), metavar="DIR")
    q.add_argument("--duration", type=float, metavar="S",
                   help="simulated time to predict, s (default: the scene's duration)")
    q.add_argument("--vtk-every", type=int, default=1, metavar="K",
                   help="write every K-th frame to the VTK series (0: none)")
    q.add_argument("--start", choices=["mpm", "rest"], default="mpm",
                   help="first frames: mpm runs the MPM at the model's spacing for the "
                        "model's C history frames (the state its training saw); rest starts "
                        "from C frames at rest")
    q.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    q.add_argument("--device", default="cpu", help="cpu or cuda")
    q.set_defaults(func=_cmd_rollout)


def _cmd_rollout(args: argparse.Namespace) -> int:
    import torch

    from minority.gns.rollout import RolloutError
    from minority.gns.runtime import tune_allocator
    from minority.sim.scene import SceneError, scene_path
    from minority.warmstart import predict_scene

    if (status := missing("oracle rollout", args.checkpoint)) is not None:
        return status
    tune_allocator()
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        p = predict_scene(args.checkpoint, scene_path(args.scene), args.duration, args.start,
                          args.device, progress=True, log=sys.stderr)
    except (SceneError, ValueError, KeyError) as exc:  # CheckpointError, a scene it cannot seed
        return _fail("rollout", exc, BAD_INPUT)
    except (RolloutError, OSError) as exc:
        return _fail("rollout", exc, FAILED)
    try:
        h5 = p.write(args.out, args.vtk_every)
    except OSError as exc:
        return _fail("rollout", exc, FAILED)
    t = p.timing
    print(f"rollout: {len(p.positions) - 1} frames in {p.wall_s:.1f} s (graph {t['graph_s']:.1f} "
          f"s, model {t['model_s']:.1f} s, {t['clamped']} positions clamped to the domain) "
          f"-> {h5}", file=sys.stderr)
    return 0


# --- spec -------------------------------------------------------------------------------

def _spec_parser(osub) -> None:
    q = command(osub, "spec", help="derive a render spec from a rollout",
                description="Find the predicted events (failure onset, fastest motion, end of "
                            "runout), plan a side view over the initiation and top and aerial "
                            "views over the runout, framed on the predicted extent; spend the "
                            "frame budget where motion is fastest; regions of interest around "
                            "the moving particles per window; colormap range from the "
                            "predicted displacement. Edit the JSON freely afterwards.")
    q.add_argument("rollout", type=Path, help="rollout.h5 from minority oracle rollout")
    add_out(q, "spec JSON to write", default=Path("spec.json"), metavar="FILE.json")
    q.add_argument("--run", metavar="ID",
                   help="run id the spec is for (default: the run id `minority sim` gives the "
                        "rollout's scene, its name)")
    q.add_argument("--frames", type=int, default=120, help="frame budget, all views together")
    q.add_argument("--width", type=int, default=1024, help="image width, px")
    q.add_argument("--height", type=int, default=768, help="image height, px")
    q.add_argument("--segments", type=int, default=4,
                   help="windows per view, each with its cadence and region")
    q.add_argument("--margin", type=float, default=0.1,
                   help="framing and colormap margin, fraction")
    q.add_argument("--no-occlusion-cull", action="store_true",
                   help="send every particle in the regions, hidden ones too (needed for "
                        "`minority serve --shadows`: hidden particles cast shadows)")
    q.add_argument("--pvcc", type=Path, metavar="DIR",
                   help="also write each view's camera as DIR/{view}.pvcc for ParaView")
    e = q.add_argument_group(
        "ensemble (an oracle that states its uncertainty; gns/ensemble.py, docs/oracle.md)",
        "With --ensemble K > 1 the rollout's checkpoint (named in the rollout file) rolls "
        "the scene out K - 1 more times from perturbed starts (each a rollout's cost: "
        "15-30 s at 1,600 particles on 2 busy cores); each event gets the interval "
        "[earliest_s, latest_s] its members span, widened by --widen; windows, cadences and "
        "regions cover every member; the spec's `deposit` holds each member's front, height "
        "and largest displacement and their band. On the 5 held-out scenes, K = 5 with the "
        "defaults put 20 of 20 actual event times and 13 of 15 deposit measures inside, for "
        "+5 % chunk bytes (python -m bench.oracle_calibration).")
    e.add_argument("--ensemble", type=_members, default=1, metavar="K",
                   help="members, the rollout itself included (1: the single rollout)")
    e.add_argument("--perturb", choices=["jitter", "friction", "both"], default="friction",
                   help="what the other members change: the start positions (jitter, 0.1 "
                        "particle spacing per axis; too little spread to cover the runs), "
                        "the friction angle (within +-2 deg), or alternately one and the "
                        "other")
    e.add_argument("--widen", type=float, default=1.0, metavar="W",
                   help="widen each interval and band on each side by W times the members' "
                        "range (intervals also by one frame interval)")
    e.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    q.set_defaults(func=_cmd_spec)


def _members(text: str) -> int:
    """--ensemble K: a whole number of members, at least 1 (a usage error otherwise)."""
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number of members >= 1")
    return k


def _ensemble_members(r: dict, args: argparse.Namespace) -> tuple[list, dict]:
    """The --ensemble's other members of rollout r ([frames, n, 3] m each, started from the
    rollout's own first C + 1 frames, perturbed) and what the provenance records of them.
    Raises ValueError (bad input: no checkpoint, no friction angle), CheckpointError,
    RolloutError, OSError."""
    import numpy as np

    from minority.gns.ensemble import EnsembleOptions, perturbed_starts, roll_members

    if not r.get("checkpoint") or r.get("friction_angle_deg") is None:
        raise ValueError("--ensemble needs a GNS rollout (from minority oracle rollout), "
                         "whose file names its checkpoint and friction angle")
    args.checkpoint = Path(str(r["checkpoint"]))
    model, _ = _load_for_cpu(args)
    c1 = model.config.input_velocities + 1
    o = EnsembleOptions(members=args.ensemble, perturb=args.perturb)
    starts = perturbed_starts(r["positions"][:c1], float(r["friction_angle_deg"]),
                              float(r["particle_spacing_m"]), o)
    trajs, labels = roll_members(model, starts[1:], np.asarray(r["bounds_m"]),
                                 len(r["positions"]) - c1, log=sys.stderr, required=0)
    return trajs, {"members": 1 + len(trajs), "perturb": o.perturb, "jitter_spacings": o.jitter,
                   "friction_spread_deg": o.friction_deg, "seed": o.seed, "widen": args.widen,
                   "perturbed": labels}


def default_run(rollout: dict) -> str:
    """The run id `minority sim` uses for the rollout's scene when no --run is given: the
    scene's name (sim.ranks: `config.run or scene.name`), as an MPM run's trajectory records
    it (scene_name) or read from the scene file a GNS rollout names. Raises SceneError."""
    from minority.sim.scene import SceneError, load_scene, scene_path

    if rollout.get("scene_name"):
        return str(rollout["scene_name"])
    if not rollout.get("scene"):
        raise SceneError("the rollout names no scene")
    return load_scene(scene_path(str(rollout["scene"]))).name


def _cmd_spec(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from minority.gns.oracle import Oracle, OracleOptions
    from minority.protocol.errors import SpecError
    from minority.protocol.paraview import write_pvcc_for_views
    from minority.protocol.trajectory import read_rollout
    from minority.sim.scene import SceneError

    if (status := missing("oracle spec", args.rollout)) is not None:
        return status
    try:
        r = read_rollout(args.rollout)
    except (ValueError, KeyError, OSError) as exc:
        return _fail("spec", exc, BAD_INPUT)
    try:
        run = args.run or default_run(r)
    except (SceneError, OSError) as exc:
        return _fail("spec", f"{exc}: pass --run (the run id of the sim the spec is for)",
                     BAD_INPUT)
    members, ensemble = [], {}
    if args.ensemble > 1:
        from minority.gns.rollout import RolloutError

        try:
            members, ensemble = _ensemble_members(r, args)
        except (ValueError, KeyError) as exc:  # CheckpointError, a rollout without its names
            return _fail("spec", exc, BAD_INPUT)
        except (RolloutError, OSError) as exc:
            return _fail("spec", exc, FAILED)
    try:
        options = replace(OracleOptions(), run=run, frames=args.frames, width=args.width,
                          height=args.height, segments=args.segments, margin=args.margin,
                          occlusion_cull=not args.no_occlusion_cull,
                          interval_widen=args.widen)
        oracle = Oracle(r["positions"], float(r["frame_interval_s"]), r["bounds_m"],
                        float(r["particle_spacing_m"]), options, members=members)
        spec = oracle.spec({"rollout": str(args.rollout), "checkpoint": str(r.get("checkpoint")),
                            "scene": str(r.get("scene")),
                            **({"ensemble": ensemble} if ensemble else {})})
    except (ValueError, SpecError, KeyError) as exc:
        return _fail("spec", exc, BAD_INPUT)
    try:
        spec.save(parent_made(args.out))
        cameras = write_pvcc_for_views(spec, args.pvcc) if args.pvcc else []
    except OSError as exc:
        return _fail("spec", exc, FAILED)
    p = oracle.summary()
    print(f"oracle: onset {p['onset_s']:.3f} s, peak motion {p['peak_s']:.3f} s, runout end "
          f"{p['runout_end_s']:.3f} s; displacement 0-{p['displacement_range_m'][1]:.3f} m",
          file=sys.stderr)
    if p.get("standing"):
        print(f"  no flow predicted (no particle travels {options.standing_travel:g} particle "
              f"spacing, {oracle.spacing:.3f} m): each view renders the run's start and end, "
              f"the rest of the {options.frames} frames is kept for `minority oracle follow`",
              file=sys.stderr)
    for e in spec.events:
        if e.interval_s is not None:
            print(f"  {e.name}: {e.time_s:.3f} s, ensemble of {len(oracle.each)}: "
                  f"{e.earliest_s:.3f}-{e.latest_s:.3f} s", file=sys.stderr)
    if spec.deposit is not None:
        d = spec.deposit
        print(f"  deposit: front {d.runout_m.low:.3f}-{d.runout_m.high:.3f} m, height "
              f"{d.height_m.low:.3f}-{d.height_m.high:.3f} m, displacement max "
              f"{d.displacement_max_m.low:.3f}-{d.displacement_max_m.high:.3f} m",
              file=sys.stderr)
    for v in spec.views:
        print(f"  view {v.name}: {v.t_start_s:.3f}-{v.t_end_s:.3f} s in {len(v.schedule)} windows, "
              f"every {', '.join(f'{w.every_s * 1e3:.1f}' for w in v.schedule)} ms",
              file=sys.stderr)
    print(f"spec {spec.run!r} -> {args.out}" + (f"; cameras -> {args.pvcc}/*.pvcc ({len(cameras)})"
                                                 if cameras else ""), file=sys.stderr)
    return 0


# --- preview ----------------------------------------------------------------------------

def _preview_parser(osub) -> None:
    q = command(osub, "preview", help="render a spec's views on a rollout (contact sheet)",
                description="Render each view of the spec on the rollout's frames that its "
                            "schedule selects, every particle drawn as the run's server draws "
                            "them (each label says how many the view's regions hold), a row "
                            "per view, and save one PNG to judge before the full run.")
    q.add_argument("spec", type=Path, help="spec JSON (minority oracle spec, or edited)")
    q.add_argument("rollout", type=Path, help="rollout.h5 from minority oracle rollout")
    add_out(q, "contact sheet PNG", default=Path("preview.png"), metavar="FILE.png")
    q.add_argument("--columns", type=int, default=6, help="frames per view")
    q.add_argument("--thumb-width", type=int, default=256, help="thumbnail width, px")
    q.set_defaults(func=_cmd_preview, kernels=True)


def _cmd_preview(args: argparse.Namespace) -> int:
    from minority.preview import preview
    from minority.protocol.errors import SpecError

    if (status := missing("oracle preview", args.spec, args.rollout)) is not None:
        return status
    try:
        out = preview(args.spec, args.rollout, args.out, args.columns, args.thumb_width)
    except (ValueError, SpecError) as exc:
        return _fail("preview", exc, BAD_INPUT)
    except OSError as exc:
        return _fail("preview", exc, FAILED)
    print(f"contact sheet -> {out}", file=sys.stderr)
    return 0


# --- follow -----------------------------------------------------------------------------

def _follow_parser(osub) -> None:
    from minority.protocol.session import add_network_args

    q = command(osub, "follow", help="follow a live run and re-forecast when it departs",
                description="The closed-loop oracle (docs/oracle.md, 'Following the run'): a "
                            "zenoh client of the run's server that reads the ranks' Stats, "
                            "and when the run leaves the spec's predictions (an event early "
                            "or late, motion outside the regions) puts an updated spec: at "
                            "once the timeline shifted and C+1 snapshots asked for (every "
                            "particle, one model frame apart), then the GNS rolled forward "
                            "from them to rest and the rest of the run re-planned. Server "
                            "and ranks adopt each update without stopping; each is printed "
                            "as a JSON line (reason, kind, cost) and logged with the run. "
                            "Ends when the server ends the run. Exit status 1 when no "
                            "server serves the run.")
    q.add_argument("run", help="run id (the spec's `run`)")
    q.add_argument("--scene", required=True,
                   help="the run's scene: a shipped name or a TOML path (domain, friction "
                        "angle and duration for the rollout)")
    q.add_argument("--checkpoint", type=Path,
                   help="GNS checkpoint to roll forward (default: the shipped "
                        "gns/checkpoints/column_l64_m5.pt)")
    q.add_argument("--ranks", type=int, default=0,
                   help="ranks of the run (0: the most seen sending Stats at one step)")
    q.add_argument("--max-updates", type=int, default=3, metavar="N",
                   help="re-forecasts at most")
    q.add_argument("--snapshot-lead", type=float, default=0.01, metavar="S",
                   help="first snapshot S s of simulated time after the newest Stats")
    q.add_argument("--wait", type=float, default=30.0, metavar="S",
                   help="wait this long (wall) for a server to serve the run's spec")
    q.add_argument("--timeout", type=float, metavar="S",
                   help="stop after S s of wall time even if the run goes on")
    q.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    add_network_args(q)
    q.set_defaults(func=_cmd_follow)


def _scene_of(name: str):
    """follow.Scene of a shipped scene name or TOML path (ValueError naming the problem)."""
    import tomllib

    import numpy as np

    from minority.gns.follow import Scene
    from minority.sim.scene import SceneError, scene_path

    try:
        raw = tomllib.loads(Path(scene_path(name)).read_text())
        size = np.asarray(raw["domain"]["size_m"], dtype=np.float64)
        return Scene(np.stack([np.zeros(3), size], axis=1),
                     float(raw["material"]["friction_angle_deg"]),
                     float(raw["time"]["duration_s"]))
    except (OSError, SceneError, tomllib.TOMLDecodeError, KeyError, ValueError) as exc:
        raise ValueError(f"scene {name}: cannot read its domain, friction angle and duration "
                         f"({exc!r})") from None


def _cmd_follow(args: argparse.Namespace) -> int:
    import threading

    from minority.gns.follow import Follower, FollowOptions
    from minority.protocol.session import Role, open_session, options_from_args

    if args.ranks < 0 or args.max_updates < 0 or args.snapshot_lead < 0:
        return _fail("follow", "--ranks, --max-updates and --snapshot-lead must be >= 0",
                     BAD_INPUT)
    args.checkpoint = args.checkpoint or DEFAULT_CHECKPOINT  # an absolute path: not in --help
    if (status := missing("oracle follow", args.checkpoint)) is not None:
        return status
    try:
        scene = _scene_of(args.scene)
        model, ckpt = _load_for_cpu(args)
    except (ValueError, KeyError) as exc:
        return _fail("follow", exc, BAD_INPUT)
    opts = options_from_args(args)
    opts.connect_timeout_s = args.wait
    try:
        session = open_session(opts, Role.CLIENT)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError, CredentialsError: say it, exit 1
        return _fail("follow", f"cannot reach the server: {exc}", FAILED)
    stop = threading.Event()
    follower = Follower(session, args.run, model, ckpt["stats"], scene,
                        FollowOptions(ranks=args.ranks, max_updates=args.max_updates,
                                      snapshot_lead_s=args.snapshot_lead, wait_s=args.wait),
                        log=sys.stdout)
    try:
        follower.fetch_spec()
        print(f"oracle follow: following run {args.run!r}", file=sys.stderr, flush=True)
        updates = follower.run(stop, args.timeout)
    except TimeoutError as exc:
        follower.close()
        return _fail("follow", exc, FAILED)
    except KeyboardInterrupt:
        follower.close()
        updates = follower.updates
    finally:
        session.close()
    print(f"oracle follow: {len(updates)} updates, "
          f"{sum(u.kind == 'forecast' for u in updates)} re-forecasts", file=sys.stderr)
    return 0


# --- oracle -----------------------------------------------------------------------------

STEPS = {"dataset": _dataset_parser, "export-npz": _export_npz_parser, "train": _train_parser,
         "evaluate": _evaluate_parser, "diagnose": _diagnose_parser, "ship": _ship_parser,
         "rollout": _rollout_parser, "spec": _spec_parser, "preview": _preview_parser,
         "follow": _follow_parser}  # pipeline order


def add_parser(sub) -> None:
    """Add `oracle` and its steps to the `minority` subparsers `sub`."""
    p = command(sub, "oracle", help=f"GNS surrogate: {', '.join(STEPS)}",
                description="Build the GNS training set from MPM runs (or any simulator's "
                            "runs, or a geoelements/gns npz dataset; export-npz writes one), "
                            "train the surrogate, "
                            "evaluate and diagnose it, ship a checkpoint, roll it out on a "
                            "scene, derive oracle specs and preview them. Exit status 2 on "
                            "bad input, 1 when a step fails at run time.")
    osub = p.add_subparsers(dest="oracle_command", required=True, metavar="STEP")
    for add in STEPS.values():
        add(osub)
    p.set_defaults(kernels=True)

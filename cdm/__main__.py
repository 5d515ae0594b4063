"""Train, evaluate and use a CDM model without a sweep, one subcommand per job.

Bad input (unknown config key, bad value, missing data or checkpoint) prints one ``error:`` line
naming the field and exits with status 2 before anything is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from cdm.baseline_names import BASELINES
from cdm.cli import PROG, add_command, add_out, add_set
from cdm.config import Config, config_field_paths, load_config, parse_override
from cdm.external_inputs import check_inputs
from cdm.interrupt import said_interrupted, sigterm_as_ctrl_c
from cdm.memory import check_memory
from cdm.metric_names import CD, F1, METRICS
from cdm.optim import TrainingDiverged
from cdm.single_image import DEFAULT_VIEW, MIN_IMAGE_SIDE
from cdm.train import Callback, fit

__all__ = ["main"]


def _overrides(pairs: list[str]) -> dict:
    return dict(parse_override(p) for p in pairs)


class _Progress(Callback):
    """Console callback: a tqdm bar over steps and one line per evaluation."""

    def __init__(self, total: int, start: int):
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True)

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        self.bar.n = step
        self.bar.set_postfix(loss=f"{metrics['train/loss']:.4f}", prior=f"{metrics['train/loss_prior_3d']:.4f}")

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        self.bar.write(
            f"step {step}: CD×1000 {metrics[CD.key]:.2f}  F1 {metrics[F1.key]:.3f}   baselines CD: "
            + "  ".join(f"{b} {metrics[f'baseline/{b}/{CD.name}']:.2f}" for b in BASELINES)
        )

    def on_checkpoint(self, step: int, path: Path) -> None:
        self.bar.write(f"checkpoint: {path}")


def cmd_train(args: argparse.Namespace) -> int:
    sets = _overrides(args.set)
    pc2 = None
    if args.init_from is not None:
        from cdm.io.files import open_regular
        from cdm.pc2_checkpoint import is_pc2_checkpoint, read_pc2_checkpoint

        try:  # says what the path is (missing, a folder, a device, a FIFO) rather than guessing it is missing
            open_regular(Path(args.init_from), "--init-from").close()
        except ValueError as exc:
            raise ValueError(f"{exc}; pass PC²'s checkpoint-latest.pth") from None
        if not is_pc2_checkpoint(args.init_from):
            raise ValueError(f"--init-from: {args.init_from} is not PC²'s checkpoint (no point_cloud_model.model.* "
                             "weights); continue a CDM run with --resume-from")
        pc2 = read_pc2_checkpoint(args.init_from, "--init-from")
    if args.out is not None:
        if sets.setdefault("train.out_dir", args.out) != args.out:
            raise ValueError(f"--out {args.out} and --set train.out_dir={sets['train.out_dir']} name two folders; "
                             "give one")
    cfg = pc2.config(sets, args.config) if pc2 else load_config(args.config, sets)
    check_inputs(cfg)
    check_memory([cfg], concurrent=1)
    if pc2 is not None:
        print("\n".join(pc2.describe(cfg, sets)))
        print("fine-tuning from its weights: the file's optimizer, scheduler and step are not loaded (a fresh AdamW, "
              "warm-up and step 0)", flush=True)
    print(f"training {cfg.train.steps} steps on data.kind={cfg.data.kind}, output in {cfg.train.out_dir}", flush=True)
    progress = _Progress(cfg.train.steps, 0)
    try:
        result = fit(cfg, [progress], resume_from=args.resume)
    finally:  # an error then starts on its own line, not after the bar
        progress.bar.close()
    print(f"done at step {result.step}: CD×1000 {result.metrics.get(CD.key, float('nan')):.2f}, "
          f"F1 {result.metrics.get(F1.key, float('nan')):.3f}; checkpoint {result.checkpoint_dir}")
    return 0


def cmd_train_prior(args: argparse.Namespace) -> int:
    from cdm.data import list_categories
    from cdm.prior_model import prior_config, train_prior

    cfg = prior_config(load_config(args.config, _overrides(args.set)), args.category)
    list_categories(cfg)  # an unknown category stops here, before anything is written
    out = Path(args.out) if args.out else Path(cfg.train.out_dir) / f"prior_{args.category}"
    d = cfg.diffusion
    print(f"training the {args.category} prior {cfg.train.steps} steps (β {d.beta_start:g} → {d.beta_end:g}, "
          f"T={d.num_steps}, {d.prediction}), output in {out}", flush=True)
    result = train_prior(cfg, out, progress=lambda step, loss: print(f"step {step}: loss {loss:.4f}", flush=True))
    print(f"done in {result.seconds:.1f} s: {result.checkpoint}; blend with --set sampling.blend.enabled=true "
          f"--set sampling.blend.prior_checkpoint={result.checkpoint}")
    return 0


def _network(checkpoint: str, sets: dict, command: str):
    """The network of a CDM checkpoint, or of PC²'s ``checkpoint-latest.pth`` with the settings it took said."""
    from cdm.checkpoint import load_network
    from cdm.paths import names_a_uri
    from cdm.pc2_checkpoint import is_pc2_checkpoint, read_pc2_checkpoint

    if names_a_uri(checkpoint):  # the library reads local files; fetching MLflow's is the sweeps' side
        raise ValueError(f"--checkpoint: {checkpoint} is a URI and `python -m cdm` reads local files; "
                         f"`cdm-lab {command} --checkpoint {checkpoint}` fetches an MLflow artifact (runs:/…) first")
    if Path(checkpoint).suffix == ".json" or not is_pc2_checkpoint(checkpoint):  # a checkpoint.json is no torch file
        return load_network(checkpoint, sets)
    pc2 = read_pc2_checkpoint(checkpoint)
    loaded = load_network(None, pc2.config(sets).flat())
    print("\n".join(pc2.describe(loaded.config, sets)), flush=True)
    return loaded


def cmd_evaluate(args: argparse.Namespace) -> int:
    from cdm.data import build_dataset
    from cdm.evaluate import build_eval_set, run_evaluation

    cfg, network, diffusion, device = _network(args.checkpoint, _overrides(args.set), args.command)
    eval_set = build_eval_set(cfg, build_dataset(cfg, "val"), build_dataset(cfg, "train"), cfg.eval.seed)
    out = run_evaluation(network, diffusion, eval_set, cfg, device, Path(args.out) if args.out else None)
    names = sorted(k for k in out.metrics if k.rsplit("/", 1)[-1] in METRICS)
    for name in names:
        print(f"{name:32s} {out.metrics[name]:10.4f}")
    return 0


def _load_image(path: Path, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """RGB ``(3, S, S)`` in [0, 1] and mask ``(1, S, S)`` of the file ``path`` (:func:`cdm.single_image.image_tensors`:
    alpha if present, else pixels unlike the corners)."""
    import cv2

    from cdm.io.images import read_image
    from cdm.single_image import image_tensors

    raw = read_image(path, cv2.IMREAD_UNCHANGED, "--image")
    if raw is None:
        raise ValueError(f"--image: cannot read {path} as an image")
    height, width = raw.shape[:2]
    if MIN_IMAGE_SIDE <= min(height, width) and min(height, width) * 4 < size:
        print(f"warning: --image {path} is {width}×{height} pixels, enlarged {size / min(height, width):.0f}× to "
              f"{size}×{size}: expect a blurry input and a poor reconstruction", file=sys.stderr)
    if raw.ndim == 3 and raw.shape[2] in (3, 4):  # OpenCV reads BGR(A)
        raw = cv2.cvtColor(raw, cv2.COLOR_BGR2RGB if raw.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return image_tensors(raw, size, "--image", str(path))


def _output_folder(out: Path) -> Path | None:
    """The missing folder ``--ply`` needs, if any: inside the working directory it is created (and
    said so); elsewhere a missing folder is refused, so a typo does not scatter folders over the disk."""
    folder = out.resolve().parent
    if folder.is_dir():
        return None
    if not folder.is_relative_to(Path.cwd().resolve()):
        raise ValueError(
            f"--ply: folder {folder} does not exist and lies outside the working directory; create it first"
        )
    return folder


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from cdm.diffusion import SamplerSettings
    from cdm.evaluate import reconstruct, write_ply
    from cdm.single_image import LookAt, image_batch

    out_folder = _output_folder(Path(args.ply))
    cfg, network, diffusion, device = _network(args.checkpoint, _overrides(args.set), args.command)
    image, mask = _load_image(Path(args.image), cfg.data.image_size)
    view = LookAt(args.elev, args.azim, args.dist, args.focal)
    batch = image_batch(image, mask, cfg, view, Path(args.image).stem).to(device)
    gen = torch.Generator(device=device).manual_seed(args.seed)
    bar = tqdm(total=len(diffusion.timesteps(SamplerSettings.from_config(cfg.diffusion))), unit="step")
    cloud = reconstruct(network, diffusion, batch, cfg, gen, progress=lambda i, n: bar.update(1))
    bar.close()
    if out_folder is not None:
        print(f"creating folder {out_folder}")
    out = write_ply(Path(args.ply), cloud[0], "--ply")
    print(f"wrote {cloud.shape[1]} points to {out} (extent {cloud[0].abs().max().item():.3f})")
    return 0


def cmd_prepare(args: argparse.Namespace) -> int:
    from cdm.data.prepare import prepare, prepare_config

    dataset, cfg = prepare_config(_overrides(args.set), args.root)
    report = prepare(dataset, cfg, Path(args.out), depth_maps=args.depth_maps and Path(args.depth_maps))
    print(f"prepared {report.out}: {report.written} shards written, {report.skipped} already complete; "
          f"train with --set data.kind={cfg.data.kind} --set data.root={report.out}")
    return 0


def cmd_check_data(args: argparse.Namespace) -> int:
    from cdm.data import build_dataset
    from cdm.data.checks import MIN_INSIDE, check_masks

    cfg = load_config(args.config, _overrides(args.set))
    failed = total = 0
    for split in ("train", "val"):
        dataset = build_dataset(cfg, split)
        for i in range(len(dataset)):
            check = check_masks(dataset, i)
            total += 1
            if not check.passed:
                failed += 1
                bad = [f"view {v}: {f:.2f}" for v, f in enumerate(check.fractions.tolist()) if f < MIN_INSIDE]
                print(f"FAIL {split} {check.object_id}: ground truth inside the mask on {', '.join(bad)}")
    print(
        f"{total - failed}/{total} objects pass (every view with a mask holds >= {MIN_INSIDE:.0%} of the "
        "projected ground truth)" + ("" if not failed else "; a cloud in the wrong frame or a wrong camera does this")
    )
    return 1 if failed else 0


def cmd_fields(args: argparse.Namespace) -> int:
    defaults = Config().flat()
    for path in config_field_paths():
        print(f"{path:28s} {defaults[path]!r}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from cdm.checkpoint import CHECKPOINT_FILE, convert_legacy

    if (Path(args.new) / CHECKPOINT_FILE).exists():
        raise ValueError(f"NEW: {args.new} holds a checkpoint already; name an empty or new folder")
    print(f"converted: {convert_legacy(args.old, args.new).parent}")
    return 0


def _add_training(sub) -> None:
    """The subcommands that train: ``train`` and ``train-prior``, in ``sub`` (``add_subparsers``' result)."""
    p = add_command(sub, "train", "train a model from a config file", "--config configs/quick.yaml --out runs/quick")
    p.add_argument("--config", metavar="FILE",
                   help="YAML config (groups data/model/diffusion/priors/train/eval); defaults if omitted")
    add_set(p, "priors.lambda_3d=0.5")
    add_out(p, "checkpoints/ and the evaluation's files (default: train.out_dir, runs/cdm)")
    p.add_argument("--resume-from", dest="resume", metavar="DIR",
                   help="a CDM checkpoint folder (<out>/checkpoints/step_N) to continue from, step and optimizer too")
    p.add_argument("--init-from", metavar="FILE",
                   help="PC²'s checkpoint-latest.pth: fine-tune its network from its weights (not its optimizer)")
    p.set_defaults(func=cmd_train)
    p = add_command(sub, "train-prior", "train an unconditional category prior for BDM blending (sampling.blend)",
                    "--category chair --set train.steps=2000")
    p.add_argument("--category", required=True, help="the one category the prior models, e.g. chair")
    p.add_argument("--config", metavar="FILE",
                   help="YAML config (data/model/diffusion/train); BDM's prior schedule unless it sets "
                   "diffusion.beta_*")
    add_set(p, "train.steps=2000")
    add_out(p, "the prior's checkpoint folder (default: <train.out_dir>/prior_<category>)")
    p.set_defaults(func=cmd_train_prior)


def _add_checkpoint_users(sub) -> None:
    """The subcommands that read a checkpoint: ``evaluate`` and ``reconstruct``."""
    p = add_command(sub, "evaluate", "score a checkpoint on the held-out split",
                    "--checkpoint runs/cdm/checkpoints/step_0001500 --out eval/")
    p.add_argument("--checkpoint", required=True, metavar="PATH",
                   help="a CDM checkpoint (folder or checkpoint.json) or PC²'s checkpoint-latest.pth")
    add_set(p, "eval.num_objects=20 (the checkpoint's config is the base)")
    add_out(p, "PLY clouds, PNG panels and CSV metrics (default: print the metrics only)")
    p.set_defaults(func=cmd_evaluate)
    p = add_command(sub, "reconstruct", "reconstruct a point cloud from one image",
                    "--checkpoint runs/cdm/checkpoints/step_0001500 --image chair.png --ply chair.ply")
    p.add_argument("--checkpoint", required=True, metavar="PATH",
                   help="a CDM checkpoint (folder or checkpoint.json) or PC²'s checkpoint-latest.pth")
    p.add_argument("--image", required=True, metavar="FILE",
                   help=f"the input photo: PNG/JPEG, grey, RGB or RGBA (alpha = mask), at least {MIN_IMAGE_SIDE} "
                   "pixels a side")
    p.add_argument("--ply", required=True, metavar="FILE", help="the point cloud to write, ASCII PLY (x y z per point)")
    add_set(p, "diffusion.sample_steps=50 (the checkpoint's config is the base)")
    for name, what in (("elev", "camera elevation in degrees"), ("azim", "camera azimuth in degrees"),
                       ("dist", "camera distance in world units"), ("focal", "focal length in NDC units")):
        default = getattr(DEFAULT_VIEW, name)
        p.add_argument(f"--{name}", type=float, default=default, help=f"{what} (default {default:g})")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampler's noise, an integer (default 0)")
    p.set_defaults(func=cmd_reconstruct)


def _add_data_and_config(sub) -> None:
    """The subcommands of data, config and old checkpoints: ``prepare``, ``check-data``, ``fields``, ``convert``."""
    p = add_command(sub, "prepare", "convert a data set once into per-object shards that load fast "
                    "(as Ray tasks over a cluster: cdm-lab inputs prepare)",
                    "--set data.kind=co3d --root RAW --out prepared/ --set data.categories=[teddybear]")
    p.add_argument("--root", required=True, metavar="DIR", help="the data set as published")
    add_out(p, "the shards; rerun the same command to resume", required=True)
    p.add_argument("--depth-maps", metavar="DIR", help="estimated depth maps (<object_id>/<position>.npy) to store in "
                   "the shards for priors.depth_source=maps")
    add_set(p, "data.kind=co3d (required: shapenet_r2n2 or co3d), data.image_size=224 (crop side, pixels)")
    p.set_defaults(func=cmd_prepare)
    p = add_command(sub, "check-data", "check that every ground-truth cloud projects into its own masks (exit 1 if "
                    "not)", "--set data.kind=co3d --set data.root=prepared/")
    p.add_argument("--config", metavar="FILE", help="YAML config; data.kind and data.root name the data set")
    add_set(p, "data.kind=co3d")
    p.set_defaults(func=cmd_check_data)
    p = add_command(sub, "fields", "list every config field with its default", "| grep priors")
    p.set_defaults(func=cmd_fields)
    p = add_command(sub, "convert", "rewrite a cdm 0.1.0 checkpoint.pt (read inertly) as a checkpoint folder of "
                    "safetensors and JSON", "runs/old/checkpoints/step_0001500 runs/new/step_0001500")
    p.add_argument("old", metavar="OLD", help="a 0.1.0 checkpoint folder or its checkpoint.pt")
    p.add_argument("new", metavar="NEW", help="the folder to write: checkpoint.json, model.safetensors, …")
    p.set_defaults(func=cmd_convert)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help="one of the commands below")
    for add in (_add_training, _add_checkpoint_users, _add_data_and_config):
        add(sub)
    return parser

def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with sigterm_as_ctrl_c():
            return args.func(args)
    except KeyboardInterrupt:
        return said_interrupted(f"{PROG} {args.command}")
    except ValueError as exc:
        # ConfigError and the data/checkpoint/image checks: raised at the boundary, before anything is written.
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"error: training diverged: {exc}", file=sys.stderr)
        return 1
    except MemoryError:
        # The readers' caps (cdm/io/) come first; what still runs out names the command's inputs.
        inputs = ", ".join(
            f"--{k.replace('_', '-')} {v}"
            for k in ("root", "config", "checkpoint", "image", "depth_maps")
            if (v := getattr(args, k, None))
        )
        print(f"error: out of memory in `{PROG} {args.command}` ({inputs or 'no input files'}); "
              "check those inputs' sizes, or free memory", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

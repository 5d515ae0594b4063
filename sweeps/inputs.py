"""Make a data set's inputs for the paper profile on Ray: prepared shards, depth maps, MSN's weights checked.

One subcommand per step, each resumable (what exists is kept), and ``all`` for every step of one
published data set, which first prints what is done and what remains::

    cdm-lab inputs prepare --set data.kind=co3d --root RAW --out PREPARED [--set data.categories=[teddybear]]
    cdm-lab inputs depth --views VIEWS --model DIR_OR_HUB_ID --out $CDM_INPUTS/depth_maps
    cdm-lab inputs all --set data.kind=co3d --root RAW --out PREPARED --inputs $CDM_INPUTS --model DIR_OR_HUB_ID

Work goes out as Ray tasks (``sweeps/execute/fanout.py``) over the cluster at ``--address`` /
``RAY_ADDRESS``, else a local cluster bound to 127.0.0.1; every node must see ``--out`` (a shared
file system). ``cdm-lab prepare`` does the same shards in one process, byte for byte. Exit 0 when
all is made, 1 with the list of items that failed (the others are made), 2 on bad input, or when
``all`` finds MSN's weights missing (it says how to fetch them: nothing is downloaded here).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/inputs.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cdm.cli import add_command, add_out, add_set, command_parser
from cdm.config import load_config, parse_override
from cdm.data.prepare import check_out, prepare_config, start
from cdm.external_inputs import MSN_URL
from cdm.interrupt import said_interrupted, sigterm_as_ctrl_c, take_sigterm_as_ctrl_c
from cdm.io.files import file_sha256
from cdm.io.json import read_json
from cdm.io.write import write_atomic
from cdm.model.encoder import load_msn_state_dict
from cdm.tools.estimate_depth import find_views
from cdm.tools.export_views import export_views
from sweeps.plan.address import given_address, reach

__all__ = ["build_parser", "main"]

MSN_FILE = Path("msn") / "vits16_800ep.pth.tar"
"""Where the paper profile reads MSN's ViT-S/16 under ``$CDM_INPUTS`` (sweeps/profiles.yaml)."""
RECORD = "inputs.json"
"""Under ``--inputs``: the sha256 of the weights file first checked, so a changed file is noticed."""


def _sets(args: argparse.Namespace) -> dict:
    return dict(parse_override(s) for s in args.set)


def _connect(address: str | None) -> tuple[float, float]:
    """Join or start the cluster (heavy: only once the input is checked); its CPUs and GPUs."""
    import ray

    from sweeps.execute.cluster import connect

    connect(address)
    take_sigterm_as_ctrl_c()  # ray.init replaced it with Ray's own, after which SIGTERM aborted the process (-6)
    resources = ray.cluster_resources()
    return float(resources.get("CPU", 1.0)), float(resources.get("GPU", 0.0))


def _shards(args: argparse.Namespace) -> list:
    from sweeps.execute.fanout import prepare_shards

    prep = start(*prepare_config(_sets(args), args.root), Path(args.out))
    cpus, _ = _connect(args.address)
    written, before, failures = prepare_shards(prep, cpus)
    print(f"prepared {prep.out}: {written} shards written, {before} already complete")
    return failures


def _depth(views: Path, args: argparse.Namespace) -> list:
    from cdm.tools.estimate_depth import load_estimator, write_manifest
    from sweeps.execute.fanout import estimate_depth

    found = find_views(views)
    probe = load_estimator(args.model, "cpu", args.predicts)  # the model loads, and what it predicts, before Ray starts
    write_manifest(Path(args.depth_out), args.model, probe.disparity)
    cpus, gpus = _connect(args.address)
    written, before, failures = estimate_depth(args.model, args.predicts, found, Path(args.depth_out), args.batch_size,
                                               cpus, gpus)
    print(f"depth maps {args.depth_out}: {written} written, {before} already there; run with "
          f"--set priors.depth_maps_disparity={str(probe.disparity).lower()}")
    return failures


def _msn(inputs: Path) -> str | None:
    """Check MSN's weights under ``inputs``: None when present, loadable and unchanged; else why not."""
    path = inputs / MSN_FILE
    if not path.is_file():
        return f"{path} is missing: curl -L --create-dirs -o {path} {MSN_URL}"
    digest, record = file_sha256(path, "model.encoder_weights"), inputs / RECORD
    seen = read_json(record, "--inputs") if record.is_file() else {}
    if not isinstance(seen, dict):
        raise ValueError(f"--inputs: {record} is not this tool's record (a JSON object); remove it to start over")
    if seen.get("msn_sha256") != digest:  # the same bytes as the first check, which loaded them, need no load
        load_msn_state_dict(path)
    if seen.setdefault("msn_sha256", digest) != digest:
        return f"{path} changed since it was first checked (sha256 {seen['msn_sha256']}, now {digest})"
    write_atomic(record, json.dumps(seen, indent=1), "--inputs")
    print(f"MSN ViT-S/16 weights: {path}, sha256 {digest}")
    return None


def _status(args: argparse.Namespace, views: Path, prepared: Path) -> None:
    """What is done and what remains, before anything runs."""
    shards = sum(1 for _ in prepared.rglob("*.safetensors")) if prepared.is_dir() else 0
    maps = sum(1 for _ in Path(args.depth_out).rglob("*.npy")) if Path(args.depth_out).is_dir() else 0
    print(
        f"MSN weights: {'present' if (Path(args.inputs) / MSN_FILE).is_file() else 'missing'}; "
        f"shards: {shards} in {prepared}; views: {'exported' if (views / 'objects.json').is_file() else 'to export'}; "
        f"depth maps: {maps} in {args.depth_out}"
    )


def _all(args: argparse.Namespace) -> tuple[list, str | None]:
    inputs = Path(args.inputs)
    _, cfg = prepare_config(_sets(args), args.root)  # a missing or unpreparable data.kind stops here
    views = inputs / "views" / cfg.data.kind
    args.depth_out = str(inputs / "depth_maps")
    check_out(Path(args.out).expanduser())  # before the status walks it
    _status(args, views, Path(args.out))
    missing = _msn(inputs)
    failures = _shards(args)
    if not (views / "objects.json").is_file():  # written last by export_views: the export is complete
        cfg = load_config(None, {**_sets(args), "data.root": args.out})
        print(f"exported {export_views(cfg, views)} views into {views}")
    return failures + _depth(views, args), missing


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser("inputs", __doc__.split("\n\n")[0], "all --set data.kind=co3d --root RAW --out prepared/ "
                            "--inputs $CDM_INPUTS --model DIR_OR_HUB_ID")
    sub = parser.add_subparsers(dest="command", required=True, metavar="STEP",
                                help="one of the steps: prepare, depth, all")
    data = argparse.ArgumentParser(add_help=False)
    data.add_argument("--root", required=True, metavar="DIR", help="the data set as published")
    add_out(data, "the prepared shards; rerun to resume", required=True)
    add_set(data, "data.kind=co3d (required: shapenet_r2n2 or co3d), data.image_size=224 (crop side, pixels)")
    model = argparse.ArgumentParser(add_help=False)
    model.add_argument("--model", required=True, metavar="DIR_OR_HUB_ID",
                       help="depth model: a local folder, or a hub id where the hub is reachable")
    model.add_argument("--predicts", choices=("depth", "disparity"),
                       help="what the model predicts, where its config does not tell (disparity: larger = nearer)")
    model.add_argument("--batch-size", type=int, default=8, metavar="N",
                       help="crops per forward pass, >= 1 (default 8)")
    ray_ = argparse.ArgumentParser(add_help=False)
    ray_.add_argument("--address", default=None, metavar="HOST:PORT|auto",
                      help="Ray cluster address (default: RAY_ADDRESS, else a local cluster on 127.0.0.1)")
    add_command(sub, "inputs prepare", "cdm-lab prepare's shards, made as Ray tasks",
                "--set data.kind=co3d --root RAW --out prepared/", parents=[data, ray_])
    p = add_command(sub, "inputs depth", "cdm-lab estimate-depth's maps, made as Ray tasks",
                    "--views views/ --model DIR_OR_HUB_ID --out depth_maps/", parents=[model, ray_])
    p.add_argument("--views", required=True, type=Path, metavar="DIR", help="output folder of cdm-lab export-views")
    add_out(p, "<object_id>/<position>.npy maps (priors.depth_maps)", dest="depth_out", required=True)
    p = add_command(sub, "inputs all", "shards, views, depth maps and the weights check of one data set",
                    "--set data.kind=co3d --root RAW --out prepared/ --inputs $CDM_INPUTS --model DIR_OR_HUB_ID",
                    parents=[data, model, ray_])
    p.add_argument("--inputs", required=True, metavar="DIR",
                   help="the $CDM_INPUTS folder: msn/, views/<kind>/, depth_maps/")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    missing = None
    try:
        with sigterm_as_ctrl_c():
            if args.command != "prepare" and args.batch_size < 1:
                raise ValueError("--batch-size must be >= 1")
            if (given := given_address(args.address)) is not None:
                reach(*given)  # before anything is written; asked again right before Ray joins it
            if args.command == "prepare":
                failures = _shards(args)
            elif args.command == "depth":
                failures = _depth(args.views, args)
            else:
                failures, missing = _all(args)
    except KeyboardInterrupt:
        return said_interrupted(f"cdm-lab inputs {args.command}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for failure in failures:
        print(f"failed: {failure.item}: {failure.error}", file=sys.stderr)
    if failures:
        print(f"{len(failures)} failed; the rest is made. Fix them and rerun the same command.", file=sys.stderr)
    if missing:
        print(f"error: MSN's weights: {missing}", file=sys.stderr)
        return 2
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

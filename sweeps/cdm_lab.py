"""One command line for CDM Lab: cdm-lab COMMAND [ARGUMENTS], each command one the project already has.

Each command hands its arguments, unchanged, to the ``main(argv)`` of the module it names: its help, its
messages and its exit codes are that command's own (``cdm-lab run SPEC`` is ``python sweeps/run.py SPEC``,
``cdm-lab train …`` is ``python -m cdm train …``), its parser made by :mod:`cdm.cli`, so that both forms say
``cdm-lab COMMAND``. A module is imported only when its command runs, so ``cdm-lab`` and ``cdm-lab --help``
answer without importing torch, Ray or MLflow.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path
from typing import NamedTuple

__all__ = ["COMMANDS", "Command", "main", "parsers", "version"]


class Command(NamedTuple):
    """A command of ``cdm-lab``: the module whose ``main(argv)`` runs it, and what it does in a line."""

    module: str
    summary: str
    subcommand: str | None = None
    """The subcommand of ``python -m cdm`` it is, put before the user's arguments; None for a module's own main."""

    def old_form(self) -> str:
        """How a user typed this command before ``cdm-lab``: still works, and still what its help shows."""
        if self.subcommand is not None:
            return f"python -m {self.module.removesuffix('.__main__')} {self.subcommand}"
        if self.module.startswith("sweeps."):
            return f"python {self.module.replace('.', '/')}.py"
        return f"python -m {self.module}"

    def parser(self) -> argparse.ArgumentParser:
        """The command's parser, as its module builds it (imports the module)."""
        parser = importlib.import_module(self.module).build_parser()
        if self.subcommand is None:
            return parser
        return _subparsers(parser)[self.subcommand]


CHECKOUT = Path(__file__).resolve().parent.parent
"""The folder above sweeps/: a git checkout when the project runs from one (``--version`` reads its commit)."""

_SWEEPS = "sweeps: Ray, Optuna and MLflow around the model"
_MODEL = "one model, without a sweep"
_TOOLS = "external inputs, written once"
COMMANDS: dict[str, tuple[str, Command]] = {
    "run": (_SWEEPS, Command("sweeps.run", "run a sweep spec: its trials on Ray, tracked in MLflow, a results table")),
    "report": (_SWEEPS, Command("sweeps.report", "rebuild a finished sweep's table, plots and panels from MLflow")),
    "register": (_SWEEPS, Command("sweeps.register", "register a finished sweep's best cell's model in MLflow")),
    "rerun": (_SWEEPS, Command("sweeps.rerun", "re-run one finished trial from its MLflow record, checked first")),
    "inputs": (_SWEEPS, Command("sweeps.inputs", "a data set's inputs for the paper profile, made as Ray tasks")),
    "train": (_MODEL, Command("cdm.__main__", "train a model from a config file", "train")),
    "train-prior": (_MODEL, Command("cdm.__main__", "train a category prior for BDM blending", "train-prior")),
    "evaluate": (_MODEL, Command("cdm.__main__", "score a checkpoint on the held-out split", "evaluate")),
    "reconstruct": (_MODEL, Command("cdm.__main__", "reconstruct a point cloud from one image", "reconstruct")),
    "prepare": (_MODEL, Command("cdm.__main__", "convert a data set once into shards that load fast", "prepare")),
    "check-data": (_MODEL, Command("cdm.__main__", "check that ground-truth clouds project into their masks",
                                   "check-data")),
    "fields": (_MODEL, Command("cdm.__main__", "list every config field with its default", "fields")),
    "convert": (_MODEL, Command("cdm.__main__", "rewrite a cdm 0.1.0 checkpoint.pt as a safetensors checkpoint",
                                "convert")),
    "export-views": (_TOOLS, Command("cdm.tools.export_views", "write the images a config's data set shows the model")),
    "estimate-depth": (_TOOLS, Command("cdm.tools.estimate_depth",
                                       "write depth maps with DINOv2's DPT head or Depth Anything")),
    "openclip-embeddings": (_TOOLS, Command("cdm.tools.openclip_embeddings",
                                            "write Table 7's per-object OpenCLIP embeddings")),
}
"""Every command, under the heading ``cdm-lab --help`` lists it beneath, in the order listed."""


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """``parser``'s subcommands by name; empty for a parser without any."""
    found = [a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(found[0]) if found else {}


def parsers() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every command's parser under its name (``inputs``' steps too, as ``inputs prepare``), in listing order."""
    for name, (_, command) in COMMANDS.items():
        parser = command.parser()
        yield name, parser
        for step, sub in _subparsers(parser).items():
            yield f"{name} {step}", sub


def version(root: Path = CHECKOUT) -> str:
    """``cdm-lab VERSION (commit HASH)``: the commit of the checkout at ``root`` when it is one (``, modified``
    with uncommitted changes), else the one pip recorded when installing from git, else ``unknown``."""
    from cdm.provenance import code_version

    try:
        dist = distribution("cdm-lab")
        number, recorded = dist.version, dist.read_text("direct_url.json")
    except PackageNotFoundError:
        number, recorded = "unknown", None
    checkout = code_version(root)
    if checkout["git_commit"] != "unknown":
        commit = checkout["git_commit"] + (", modified" if checkout["git_dirty"] == "true" else "")
    else:
        commit = json.loads(recorded or "{}").get("vcs_info", {}).get("commit_id", "unknown")
    return f"cdm-lab {number} (commit {commit})"


def _listing() -> str:
    """The commands by heading, each with its line and the command it is."""
    width = max(map(len, COMMANDS))
    lines, heading = [], None
    for name, (group, command) in COMMANDS.items():
        if group != heading:
            lines += ["", f"{group}:"] if heading else [f"{group}:"]
            heading = group
        lines.append(f"  {name:{width}}  {command.summary} ({command.old_form()})")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cdm-lab",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_listing() + "\n\ncdm-lab COMMAND --help shows a command's arguments and an example; "
        "docs/cli.md lists them all.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and the git commit, and exit")
    parser.add_argument("command", choices=COMMANDS, metavar="COMMAND", help="one of the commands below")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``argv``'s command (``sys.argv[1:]`` when None) with the arguments after it; its exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv:  # as mlflow and ray do: what there is to run
        _parser().print_help()
        return 0
    if argv == ["--version"]:
        print(version())
        return 0
    if argv[0] not in COMMANDS:
        _parser().parse_args(argv[:1])  # --help exits 0; an unknown command exits 2, naming the choices
    _, command = COMMANDS[argv[0]]
    prefix = [command.subcommand] if command.subcommand is not None else []
    if command.module != "cdm.__main__":
        return importlib.import_module(command.module).main(prefix + argv[1:])
    # The model commands read local files; a --checkpoint URI (runs:/<run id>/model) is fetched by MLflow first.
    from sweeps.fetch_checkpoint import FetchError, fetched_checkpoint

    with ExitStack() as stack:
        try:
            args = stack.enter_context(fetched_checkpoint(argv[1:]))
        except FetchError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return importlib.import_module(command.module).main(prefix + args)


if __name__ == "__main__":
    sys.exit(main())

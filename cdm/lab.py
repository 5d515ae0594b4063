"""One command line for CDM Lab: cdm-lab COMMAND [ARGUMENTS], each command one the project already has.

Each command hands its arguments, unchanged, to the ``main(argv)`` of the module it names: its help, its
messages and its exit codes are that command's own (``cdm-lab train …`` is ``python -m cdm train …``), its
parser made by :mod:`cdm.cli`, so that both forms say ``cdm-lab COMMAND``. A module is imported only when its
command runs, so ``cdm-lab`` and ``cdm-lab --help`` answer without importing torch, Ray or MLflow.

The model's commands are listed here. Other packages add theirs through Python entry points, read with
:mod:`importlib.metadata`, so that this library needs none of them to train, evaluate or reconstruct:

- ``cdm_lab.commands``: a dict ``name → (heading, Command)``, listed before the model's own;
- ``cdm_lab.checkpoint_fetchers``: ``fetch(uri, folder) -> path``, which downloads a model command's
  ``--checkpoint URI`` (``runs:/…``) into ``folder`` and returns the checkpoint's local path, raising
  ``ValueError`` with one line naming ``--checkpoint`` when it cannot. Without one, a URI is refused by the
  command itself.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import sys
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from importlib.metadata import PackageNotFoundError, distribution, entry_points
from pathlib import Path
from typing import NamedTuple

from cdm.paths import names_a_uri

__all__ = ["COMMANDS", "Command", "commands", "main", "parsers", "version"]


class Command(NamedTuple):
    """A command of ``cdm-lab``: the module whose ``main(argv)`` runs it, and what it does in a line."""

    module: str
    summary: str
    subcommand: str | None = None
    """The subcommand of ``python -m <package>`` it is, put before the user's arguments; None for a module's
    own main."""
    as_file: bool = False
    """Its old form runs the module's file (``python sweeps/run.py``) rather than ``python -m module``."""

    def old_form(self) -> str:
        """How a user typed this command before ``cdm-lab``: still works, and still what its help shows."""
        if self.subcommand is not None:
            return f"python -m {self.module.removesuffix('.__main__')} {self.subcommand}"
        if self.as_file:
            return f"python {self.module.replace('.', '/')}.py"
        return f"python -m {self.module}"

    def parser(self) -> argparse.ArgumentParser:
        """The command's parser, as its module builds it (imports the module)."""
        parser = importlib.import_module(self.module).build_parser()
        if self.subcommand is None:
            return parser
        return _subparsers(parser)[self.subcommand]


CHECKOUT = Path(__file__).resolve().parent.parent
"""The folder above cdm/: a git checkout when the project runs from one (``--version`` reads its commit)."""

COMMANDS_GROUP = "cdm_lab.commands"
FETCHERS_GROUP = "cdm_lab.checkpoint_fetchers"

_MODEL = "one model, without a sweep"
_TOOLS = "external inputs, written once"
_MAIN = "cdm.__main__"
COMMANDS: dict[str, tuple[str, Command]] = {
    "train": (_MODEL, Command(_MAIN, "train a model from a config file", "train")),
    "train-prior": (_MODEL, Command(_MAIN, "train a category prior for BDM blending", "train-prior")),
    "evaluate": (_MODEL, Command(_MAIN, "score a checkpoint on the held-out split", "evaluate")),
    "reconstruct": (_MODEL, Command(_MAIN, "reconstruct a point cloud from one image", "reconstruct")),
    "prepare": (_MODEL, Command(_MAIN, "convert a data set once into shards that load fast", "prepare")),
    "check-data": (_MODEL, Command(_MAIN, "check that ground-truth clouds project into their masks", "check-data")),
    "fields": (_MODEL, Command(_MAIN, "list every config field with its default", "fields")),
    "convert": (_MODEL, Command(_MAIN, "rewrite a cdm 0.1.0 checkpoint.pt as a safetensors checkpoint", "convert")),
    "export-views": (_TOOLS, Command("cdm.tools.export_views", "write the images a config's data set shows the model")),
    "estimate-depth": (_TOOLS, Command("cdm.tools.estimate_depth",
                                       "write depth maps with DINOv2's DPT head or Depth Anything")),
    "openclip-embeddings": (_TOOLS, Command("cdm.tools.openclip_embeddings",
                                            "write Table 7's per-object OpenCLIP embeddings")),
}
"""The model library's own commands, under the heading ``cdm-lab --help`` lists each beneath, in the order listed."""


@functools.cache
def commands() -> dict[str, tuple[str, Command]]:
    """Every command: those the installed ``cdm_lab.commands`` entry points add (in their names' order), then
    :data:`COMMANDS`, which keep their meaning whatever a plug-in names."""
    added: dict[str, tuple[str, Command]] = {}
    for point in sorted(entry_points(group=COMMANDS_GROUP), key=lambda p: p.name):
        added.update(point.load())
    return {**{k: v for k, v in added.items() if k not in COMMANDS}, **COMMANDS}


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """``parser``'s subcommands by name; empty for a parser without any."""
    found = [a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(found[0]) if found else {}


def parsers() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every command's parser under its name (``inputs``' steps too, as ``inputs prepare``), in listing order."""
    for name, (_, command) in commands().items():
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
    listed = commands()
    width = max(map(len, listed))
    lines, heading = [], None
    for name, (group, command) in listed.items():
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
    parser.add_argument("command", choices=commands(), metavar="COMMAND", help="one of the commands below")
    return parser


_CHECKPOINT = "--checkpoint"


def _checkpoint_value(argv: list[str]) -> tuple[int, str] | None:
    """(index in ``argv``, value) of ``--checkpoint VALUE`` or ``--checkpoint=VALUE``; None when absent."""
    for i, arg in enumerate(argv):
        if arg == _CHECKPOINT and i + 1 < len(argv):
            return i + 1, argv[i + 1]
        if arg.startswith(_CHECKPOINT + "="):
            return i, arg.removeprefix(_CHECKPOINT + "=")
    return None


@contextmanager
def fetched_checkpoint(argv: list[str]) -> Iterator[list[str]]:
    """``argv`` with a ``--checkpoint`` URI replaced by the local copy a ``cdm_lab.checkpoint_fetchers`` entry
    point made of it, in a temporary folder removed when the context ends; ``argv`` itself when it names a local
    checkpoint or no fetcher is installed (the command then refuses the URI in its own words).

    Raises:
        ValueError: the fetcher could not resolve or download the URI (one line, naming ``--checkpoint``).
    """
    found = _checkpoint_value(argv)
    fetchers = sorted(entry_points(group=FETCHERS_GROUP), key=lambda p: p.name) if found else []
    if found is None or not names_a_uri(found[1]) or not fetchers:
        yield argv
        return
    i, uri = found
    with tempfile.TemporaryDirectory(prefix="cdm-checkpoint-") as tmp:
        local = str(fetchers[0].load()(uri, Path(tmp)))
        yield [*argv[:i], local if argv[i] == uri else f"{_CHECKPOINT}={local}", *argv[i + 1:]]


def main(argv: list[str] | None = None) -> int:
    """Run ``argv``'s command (``sys.argv[1:]`` when None) with the arguments after it; its exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv:  # as mlflow and ray do: what there is to run
        _parser().print_help()
        return 0
    if argv == ["--version"]:
        print(version())
        return 0
    if argv[0] not in commands():
        _parser().parse_args(argv[:1])  # --help exits 0; an unknown command exits 2, naming the choices
    _, command = commands()[argv[0]]
    prefix = [command.subcommand] if command.subcommand is not None else []
    if command.module != _MAIN:
        return importlib.import_module(command.module).main(prefix + argv[1:])
    with ExitStack() as stack:  # the model commands read local files: a --checkpoint URI is fetched first
        try:
            args = stack.enter_context(fetched_checkpoint(argv[1:]))
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return importlib.import_module(command.module).main(prefix + args)


if __name__ == "__main__":
    sys.exit(main())

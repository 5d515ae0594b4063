"""The grammar every ``cdm-lab`` command shares, on argparse: its name, ``--out`` and ``--set``.

Each command's parser is made here, so that wherever it is run from (``cdm-lab train``, ``python -m cdm
train``, ``python sweeps/run.py``) its usage line and its argument errors say ``cdm-lab COMMAND``, its help
opens with one line saying what it does and closes with one example. ``--out DIR`` is always the folder a
command writes into; a command that writes one file names that file's flag for what it holds (``--ply``).
A flag is given by its whole name: argparse's prefix matching is off, so that a removed flag (``train
--resume``, now ``--resume-from``) is an error rather than a prefix of its successor (CHANGELOG.md, 0.2.0).
"""

from __future__ import annotations

import argparse

__all__ = ["PROG", "add_command", "add_out", "add_set", "command_parser"]

PROG = "cdm-lab"
"""The one program name every usage line and argument error shows."""

_FORMAT = argparse.RawDescriptionHelpFormatter  # keeps the example's line as written


def _texts(name: str, description: str, example: str) -> dict:
    return {"prog": f"{PROG} {name}", "description": description, "epilog": f"example:\n  {PROG} {name} {example}",
            "formatter_class": _FORMAT, "allow_abbrev": False}


def command_parser(name: str, description: str, example: str) -> argparse.ArgumentParser:
    """The parser of command ``name``: ``description`` is one sentence, ``example`` the arguments of one use."""
    return argparse.ArgumentParser(**_texts(name, description, example))


def add_command(sub, name: str, description: str, example: str, parents=()) -> argparse.ArgumentParser:
    """A subcommand's parser, in ``sub`` (``add_subparsers``' result), named ``<its parent's name> name``."""
    return sub.add_parser(name.rpartition(" ")[2], help=description, parents=list(parents),
                          **_texts(name, description, example))


def add_out(parser: argparse.ArgumentParser, what: str, **kwargs) -> None:
    """``--out DIR``: the folder the command writes into; ``what`` says what lands there."""
    parser.add_argument("--out", metavar="DIR", help=f"folder to write into: {what}", **kwargs)


def add_set(parser: argparse.ArgumentParser, example: str) -> None:
    """``--set KEY=VALUE``, repeatable: one config field over the defaults and ``--config``."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help=f"override one config field, repeatable (`cdm-lab fields` lists them), e.g. {example}")


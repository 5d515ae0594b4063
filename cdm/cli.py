"""The grammar every ``cdm-lab`` command shares, on argparse: its name, ``--out``, ``--set`` and old spellings.

Each command's parser is made here, so that wherever it is run from (``cdm-lab train``, ``python -m cdm
train``, ``python sweeps/run.py``) its usage line and its argument errors say ``cdm-lab COMMAND``, its help
opens with one line saying what it does and closes with one example. ``--out DIR`` is always the folder a
command writes into; a command that writes one file names that file's flag for what it holds (``--ply``).
A renamed flag keeps its old spelling for one release, hidden from the help, with a one-line note on stderr.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["PROG", "OldSpelling", "add_command", "add_out", "add_set", "command_parser", "old_spelling"]

PROG = "cdm-lab"
"""The one program name every usage line and argument error shows."""

_FORMAT = argparse.RawDescriptionHelpFormatter  # keeps the example's line as written


def _texts(name: str, description: str, example: str) -> dict:
    return {"prog": f"{PROG} {name}", "description": description, "epilog": f"example:\n  {PROG} {name} {example}",
            "formatter_class": _FORMAT}


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


class OldSpelling(argparse.Action):
    """A renamed flag's old spelling: does what the new one does, hidden from the help, and says the new name.

    ``key`` set: the value becomes ``--set key=VALUE`` (a flag that repeated a config field).
    """

    def __init__(self, option_strings, dest, new: str, key: str | None = None, **kwargs):
        self.new, self.key = new, key
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"note: {parser.prog} {option_string} is now {self.new}; the old spelling goes in the next release",
              file=sys.stderr)
        for action in parser._actions:  # the new flag, if required, is given now (each command builds its parser anew)
            if action.dest == self.dest and action is not self:
                action.required = False
        if self.nargs == 0:  # an old switch
            setattr(namespace, self.dest, self.const)
        elif self.key is None:
            setattr(namespace, self.dest, values)
        else:
            setattr(namespace, self.dest, [*getattr(namespace, self.dest), f"{self.key}={values}"])


def old_spelling(parser: argparse.ArgumentParser, old: str, new: str, dest: str, key: str | None = None,
                 **kwargs) -> None:
    """Accept ``old`` as ``new`` (stored in ``dest``) for one release; ``key``: see :class:`OldSpelling`."""
    parser.add_argument(old, dest=dest, action=OldSpelling, new=new, key=key, **kwargs)

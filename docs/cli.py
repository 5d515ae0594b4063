"""Write docs/cli.md from the parsers of every cdm-lab command: usage, flags, example.

``python docs/cli.py`` rewrites the page; ``tests/test_lab.py`` fails while the page differs from what
this prints, so a flag added to a parser without rerunning this is caught.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # `python docs/cli.py` puts docs/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cdm.cli import PROG
from cdm.lab import commands, parsers

PAGE = Path(__file__).resolve().parent / "cli.md"
WIDTH = 100
"""Columns of the usage blocks: fixed, so the page does not depend on the terminal that wrote it."""

HEAD = f"""# Command line: `{PROG}`

Every command and flag of `{PROG}`, written by `python docs/cli.py` from the commands' own parsers (a test
fails when this page is stale). `{PROG}` alone lists the commands, `{PROG} COMMAND --help` shows one,
`{PROG} --version` prints the version and the git commit.

One grammar holds for every command:

- `--out DIR` is always the folder a command writes into; a command that writes one file names it for what it
  holds (`reconstruct --ply FILE`, `openclip-embeddings --npz FILE`).
- `--set KEY=VALUE` (repeatable) overrides one config field on every command that builds a config;
  `{PROG} fields` lists the fields.
- A flag means one thing everywhere: `run --resume` continues a sweep, `train --resume-from DIR` continues a
  training.
- A flag is typed whole (no prefix of it stands for it). The spellings 0.2.0 removed, each with the one that
  replaced it, are in [CHANGELOG.md](../CHANGELOG.md).
- The old forms run the same commands: `python sweeps/run.py SPEC` is `{PROG} run SPEC`, `python -m cdm train`
  is `{PROG} train`, `python -m cdm.tools.export_views` is `{PROG} export-views`.
"""


def _cell(text: str) -> str:
    """``text`` as Markdown shows it literally in a table cell: no column break, HTML tag or emphasis."""
    return text.replace("|", "\\|").replace("<", "&lt;").replace("*", "\\*")


def _usage(parser: argparse.ArgumentParser) -> str:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def _section(name: str, parser: argparse.ArgumentParser) -> str:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    rows = []
    for action in parser._actions:
        if not isinstance(action, argparse._HelpAction):
            flag = formatter._format_action_invocation(action).replace("|", "\\|")  # in code: no tag, no emphasis
            rows.append(f"| `{flag}` | {_cell(action.help)} |")
    lines = [f"## {PROG} {name}", "", _cell(parser.description), "", "```", _usage(parser), "```", ""]
    if rows:
        lines += ["| argument | meaning |", "|---|---|", *rows, ""]
    lines += [f"Example: `{parser.epilog.splitlines()[1].strip()}`", ""]
    return "\n".join(lines)


def render() -> str:
    """The page: the grammar, a table of contents, then each command (and each ``inputs`` step)."""
    found, listed = list(parsers()), commands()
    contents = [f"- [`{PROG} {name}`](#{PROG}-{name.replace(' ', '-')}): "
                f"{listed[name][1].summary if name in listed else parser.description}" for name, parser in found]
    return "\n".join([HEAD, "## Commands", "", *contents, "", *(_section(n, p) for n, p in found)]).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(prog="python docs/cli.py", description=__doc__.split("\n\n")[0]).parse_args(argv)
    PAGE.write_text(render(), encoding="utf-8")
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

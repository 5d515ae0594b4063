"""The README stays a newcomer's path, and no link in it or in ``docs/`` points nowhere.

Links are checked as GitHub renders them: a relative path must name a file of the repository, and a
``#fragment`` must be the slug of a heading in the file it points at (GitHub's rule: lower case, every
character but letters, digits, ``_``, ``-`` and spaces dropped, spaces turned into ``-``, a repeated
slug suffixed ``-1``, ``-2``, …).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
MAX_README_LINES = 300

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`+[^`\n]*`+")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_IMAGE = re.compile(r"!\[[^\]\n]*\]\(([^)\s]+)")
_HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.M)


def _prose(text: str) -> str:
    """``text`` without fenced code blocks: a link written inside code is not a link."""
    return _FENCE.sub("", text)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: inline code, emphasis and link targets rendered away."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").replace("*", "")
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file, repeated headings numbered as GitHub does."""
    seen: dict[str, int] = {}
    out = set()
    for heading in _HEADING.findall(_prose(path.read_text(encoding="utf-8"))):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    """Relative link and image targets of a Markdown file (web addresses left out)."""
    text = _CODE.sub("", _prose(path.read_text(encoding="utf-8")))
    return [t for t in _LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def test_slug_follows_github() -> None:
    assert slug("BDM blending (Table 2)") == "bdm-blending-table-2"
    assert slug("The main job's results") == "the-main-jobs-results"
    assert slug("Which recipe learns (1,500-step variants)") == "which-recipe-learns-1500-step-variants"
    assert slug("Run `ray start` by hand") == "run-ray-start-by-hand"
    assert slug("Table 5: H × size") == "table-5-h--size"


def test_readme_is_at_most_300_lines() -> None:
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines <= MAX_README_LINES, f"README.md has {lines} lines; move the depth into docs/ and link it"


def test_readme_keeps_the_main_jobs_table() -> None:
    # The lead refreshes this table from each new main-job run: its heading is how they find it.
    assert "\n## The main job's results\n" in README.read_text(encoding="utf-8")


def broken_links(doc: Path) -> list[str]:
    """Each relative link of ``doc`` whose file is missing, or whose ``#fragment`` names no heading there."""
    broken = []
    for target in links(doc):
        path, _, fragment = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        if not file.exists():
            broken.append(f"{target}: no such file")
        elif fragment and file.suffix == ".md" and fragment not in anchors(file):
            broken.append(f"{target}: no heading #{fragment} in {file.name}")
    return broken


def test_broken_links_are_found(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Other page\n\n## Set-up (once)\n\n## Set-up (once)\n")
    doc = tmp_path / "doc.md"
    doc.write_text("# Here\n\n[a](other.md#set-up-once) [b](other.md#set-up-once-1) [c](#here) [d](https://x.org/y)\n"
                   "[e](missing.md) [f](other.md#set-up) [g](#nowhere) ![h](pic.png)\n"
                   "```\n[i](in-code.md)\n```\n`[j](in-span.md)`\n")
    assert broken_links(doc) == ["missing.md: no such file", "other.md#set-up: no heading #set-up in other.md",
                                 "#nowhere: no heading #nowhere in doc.md", "pic.png: no such file"]


@pytest.mark.parametrize("doc", [README, *DOCS], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(doc: Path) -> None:
    broken = broken_links(doc)
    assert not broken, f"{doc.relative_to(ROOT)}: " + "; ".join(broken)


def test_every_image_the_readme_shows_exists() -> None:
    images = _IMAGE.findall(_prose(README.read_text(encoding="utf-8")))
    assert len(images) >= 6, images
    missing = [i for i in images if not (ROOT / i).is_file()]
    assert not missing, missing


# The README's result tables copy numbers measured in docs/local-results.md; a copy that drifts from its
# source fails here. Each pair: README section, the column there, the local-results section and its column.
LOCAL_RESULTS = ROOT / "docs" / "local-results.md"
COPIED_COLUMNS = [
    ("The main job's results", 0, "The main job on", {
        "eval/f1": "eval/f1", "paper F1": "paper eval/f1", "eval/cd": "eval/cd", "Δf1": "Δf1", "verdict": "verdict"
    }),
    ("Reading an ablation", 0, "The main job on 2026-12-03", {"one seed: Δf1": "Δf1"}),
]
"""(README section, which of its tables, local-results.md section, README column → local column). A section
is the first whose heading starts so: local-results.md puts the newest main job first, so the README's
refreshed table is held against the run it came from. Columns are named by how their header starts; a
column compares what each cell leads with, ``verdict`` its whole text."""


def _section(text: str, heading: str) -> str:
    """The body of the first ``## heading…`` section (to the next heading of that level or higher)."""
    body = re.split(rf"^## {re.escape(heading)}.*\n", text, maxsplit=1, flags=re.M)[1]
    return re.split(r"^##? ", body, flags=re.M)[0]


def _markdown_tables(text: str) -> list[list[dict[str, str]]]:
    """Every pipe table of ``text``, each a list of rows (header → cell text)."""
    tables, lines = [], text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("|") and not (i and lines[i - 1].startswith("|")) and lines[i + 1].startswith("|---"):
            header = [c.strip() for c in line.strip("|").split("|")]
            rows = []
            for row in lines[i + 2:]:
                if not row.startswith("|"):
                    break
                rows.append(dict(zip(header, (c.strip() for c in row.strip("|").split("|")))))
            tables.append(rows)
    return tables


def _printed_table(text: str) -> list[dict[str, str]]:
    """The table the runner prints, in the first code block of ``text``: columns cut where its dashes start, a
    header wrapped over the lines between the title and the ``cell`` line read as one."""
    block = text.split("```\n", 2)[1].splitlines()
    start = next(i for i, line in enumerate(block) if line.startswith("cell "))
    cuts = [m.start() for m in re.finditer(r"-+", block[start + 1])] + [None]
    heads = block[1:start + 1]
    header = [" ".join(filter(None, (line[a:b].strip() for line in heads))) for a, b in zip(cuts, cuts[1:])]
    rows = []
    for line in block[start + 2:]:
        if not line.strip():
            break
        rows.append({h: line[a:b].strip() for h, a, b in zip(header, cuts, cuts[1:])})
    return rows


def _row_name(name: str) -> str:
    """A row's cell as both pages write it: ``point_size=0.04``, ``baseline: category_mean``."""
    name = re.sub(r" (★|\(tied\))$", "", re.sub(r" \([^)]*\)$", "", name) if name.startswith("baseline") else name)
    return name.lower().replace("baseline: ", "baseline:").replace(" ", "_").replace("baseline:", "baseline: ")


def _column(row: dict[str, str], start: str) -> str:
    return next(v for h, v in row.items() if h.startswith(start))


def _lead(text: str) -> str:
    """What a cell leads with: its number (``−0.026 [−0.046, −0.006]`` → ``-0.026``), else its first word."""
    return (re.findall(r"^[-+]?\d+(?:\.\d+)?|^\w+", text.replace("−", "-")) or [""])[0]


def copied_differences(readme: str, local: str) -> list[str]:
    """Each README number (or verdict) of :data:`COPIED_COLUMNS` that differs from docs/local-results.md's."""
    out = []
    for readme_section, index, local_section, columns in COPIED_COLUMNS:
        ours = _markdown_tables(_section(readme, readme_section))[index]
        body = _section(local, local_section)
        table = _printed_table(body) if "```" in body else _markdown_tables(body)[0]
        theirs = {_row_name(r["cell"]): r for r in table}
        assert len(ours) >= 5 and len(theirs) >= 5  # both tables were found
        for row in ours:
            source = theirs.get(_row_name(row["cell"]))
            for mine, their in columns.items():
                a = _column(row, mine)
                b = _column(source, their) if source else "no such row"
                same = a == b if mine == "verdict" else _lead(a) == _lead(b)
                if not same:
                    out.append(f"{readme_section}: {row['cell']} {mine} {a!r}, local-results.md {local_section}: {b!r}")
    return out


def test_the_readme_copies_its_numbers_from_local_results() -> None:
    differences = copied_differences(README.read_text(encoding="utf-8"), LOCAL_RESULTS.read_text(encoding="utf-8"))
    assert not differences, "\n".join(differences)


def test_a_readme_number_that_drifts_from_local_results_is_found() -> None:
    readme, local = README.read_text(encoding="utf-8"), LOCAL_RESULTS.read_text(encoding="utf-8")
    assert "| point_size=0.02 | 154.3 | 0.582 | | 38.18 |" in readme and "−0.026 [−0.046, −0.006], worse |" in readme
    row = "| point_size=0.02 | 154.3 | 0.582 | | 38.18 |"
    drifted = readme.replace(row, row.replace("38.18", "38.81")).replace(
        "−0.026 [−0.046, −0.006], worse |", "−0.062 [−0.046, −0.006], worse |"
    )
    assert copied_differences(drifted, local) == [
        "The main job's results: point_size=0.02 eval/cd '38.81', local-results.md The main job on: '38.18'",
        "Reading an ablation: point_size=0.08 one seed: Δf1 '−0.062 [−0.046, −0.006], worse', "
        "local-results.md The main job on 2026-12-03: '−0.026 [−0.046, −0.006]'",
    ]


def _time_figures(text: str) -> list[str]:
    """Durations written in ``text`` (``16.7 min``, ``~8 minutes``, ``12 min 28 s``), the promise ``≤ 15 min`` aside."""
    return re.findall(r"(?<!≤ )\b\d+(?:\.\d+)? ?(?:min|minutes)\b", text)


def test_the_main_jobs_time_is_measured_in_one_place_that_the_others_cite():
    """docs/local-results.md holds the main job's measured time; the README's sections on the main job and the
    quick config, configs/quick.yaml and the local profile cite it and write no figure of their own."""
    results = LOCAL_RESULTS
    assert "the-main-jobs-time" in anchors(results)
    assert _time_figures(_section(results.read_text(encoding="utf-8"), "The main job's time"))
    readme = README.read_text(encoding="utf-8")
    quick = (ROOT / "configs" / "quick.yaml").read_text(encoding="utf-8")
    local = (ROOT / "sweeps" / "profiles.yaml").read_text(encoding="utf-8").split("\nlocal:", 1)[1].split("\npaper:")[0]
    citing = {
        "README.md, The main job's results": _section(readme, "The main job's results"),
        "README.md, Train one model": _section(readme, "Train one model"),
        "configs/quick.yaml": quick,
        "sweeps/profiles.yaml, local": local,
    }
    assert {where: _time_figures(text) for where, text in citing.items()} == {where: [] for where in citing}
    assert all("local-results.md" in text for text in citing.values())
    planted = "the sweep took 16.7 min (17 min 43 s); ~8 minutes; ≤ 15 min"
    assert _time_figures(planted) == ["16.7 min", "17 min", "8 minutes"]


QUICK_START = [
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e . && "
    "python sweeps/run.py sweeps/point_size.yaml",
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e \".[test]\" && "
    "python -m pytest",
]
"""The README's two quick-start commands, the main job and the test suite: what a newcomer copies first, so a
new command line (``cdm-lab``) adds a section and leaves these as they are."""


def test_the_quick_start_keeps_its_two_commands() -> None:
    section = _section(README.read_text(encoding="utf-8"), "Quick start")
    assert re.findall(r"^```bash\n(.+)\n```$", section, re.M) == QUICK_START

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


def _time_figures(text: str) -> list[str]:
    """Durations written in ``text`` (``16.7 min``, ``~8 minutes``, ``12 min 28 s``), the promise ``≤ 15 min`` aside."""
    return re.findall(r"(?<!≤ )\b\d+(?:\.\d+)? ?(?:min|minutes)\b", text)


def _section(text: str, heading: str) -> str:
    return text.split(f"\n{heading}\n", 1)[1].split("\n## ", 1)[0]


def test_the_main_jobs_time_is_measured_in_one_place_that_the_others_cite():
    """docs/local-results.md holds the main job's measured time; the README's sections on the main job and the
    quick config, configs/quick.yaml and the local profile cite it and write no figure of their own."""
    results = ROOT / "docs" / "local-results.md"
    assert "the-main-jobs-time" in anchors(results)
    assert _time_figures(_section(results.read_text(encoding="utf-8"), "## The main job's time"))
    readme = README.read_text(encoding="utf-8")
    quick = (ROOT / "configs" / "quick.yaml").read_text(encoding="utf-8")
    local = (ROOT / "sweeps" / "profiles.yaml").read_text(encoding="utf-8").split("\nlocal:", 1)[1].split("\npaper:")[0]
    citing = {
        "README.md, The main job's results": _section(readme, "## The main job's results"),
        "README.md, Train one model": _section(readme, "## Train one model"),
        "configs/quick.yaml": quick,
        "sweeps/profiles.yaml, local": local,
    }
    assert {where: _time_figures(text) for where, text in citing.items()} == {where: [] for where in citing}
    assert all("local-results.md" in text for text in citing.values())
    planted = "the sweep took 16.7 min (17 min 43 s); ~8 minutes; ≤ 15 min"
    assert _time_figures(planted) == ["16.7 min", "17 min", "8 minutes"]

"""One-way architecture: no import cycle in cdm/ or sweeps/, the model library knows nothing of the
sweep stack (Ray, MLflow, Optuna) or of sweeps/, and ``docs/ARCHITECTURE.md`` draws what the code does:
every module is named in it and every arrow it draws is an import.

Imports are read with ``ast`` from the source, every one of them: module level, inside functions
(deferred imports) and under ``TYPE_CHECKING``, so a cycle hidden behind a lazy import counts too.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cdm", "sweeps")
FORBIDDEN_IN_CDM = ("ray", "mlflow", "optuna", "sweeps")
DOC = ROOT / "docs" / "ARCHITECTURE.md"
ARROW = "─►"
# A module as the doc writes it: a file (`cdm/data/views.py`) or a package folder (`cdm/data/`, `cdm/`).
DOC_PATH = re.compile(r"(?<![\w/.])((?:cdm|sweeps)/(?:[A-Za-z_]\w*/)*(?:[A-Za-z_]\w*\.py)?)(?![\w*.])")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def _imported(path: Path, name: str, known: set[str]) -> set[str]:
    """Modules of ``known`` that the file imports, anywhere in it; ``from a import b`` counts ``a.b``
    when that is a module, else ``a``; relative imports are resolved against ``name``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            # `import cdm.data.views` also imports its packages; the innermost known module names the edge.
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imported(path, name, known) for name, path in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a path ``[a, b, …, a]``, or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    for root in sorted(graph):
        if root in state:
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def test_the_cycle_finder_finds_a_planted_cycle_and_accepts_a_tree():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_import_reader_sees_lazy_relative_and_type_checking_imports(tmp_path, monkeypatch):
    package = tmp_path / "cdm"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from cdm import b\n"
        "def f():\n    from .c import thing\n    import cdm.d.e\n"
    )
    monkeypatch.setattr(f"{__name__}.ROOT", tmp_path)
    assert _imported(package / "a.py", "cdm.a", {"cdm", "cdm.a", "cdm.b", "cdm.c", "cdm.d", "cdm.d.e"}) == {
        "cdm.b",
        "cdm.c",
        "cdm.d.e",
    }


def test_no_import_cycle_in_cdm_or_sweeps():
    graph = _graph()
    assert len(graph) > 30 and "cdm.train" in graph and "sweeps.execute.trial" in graph  # the walk found the code
    cycle = _cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


@pytest.mark.parametrize("name", sorted(n for n in _modules() if n == "cdm" or n.startswith("cdm.")))
def test_the_model_library_does_not_import_the_sweep_stack(name):
    tree = ast.parse(_modules()[name].read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            roots.add(node.module.split(".")[0])
    assert not roots & set(FORBIDDEN_IN_CDM), f"{name} imports {sorted(roots & set(FORBIDDEN_IN_CDM))}"


def _doc_arrows(text: str) -> list[tuple[int, str, str]]:
    """``(line number, importer, imported)`` for every arrow in the doc's code blocks.

    The doc's one convention: ``A ─► B, C ─► D`` says A imports B and C, and C imports D; the
    importer of an arrow is the last module written before it, the imported ones all modules
    written between it and the next arrow. An arrow with no module on either side is returned with
    an empty name, so that the test reports it.
    """
    arrows, in_code = [], False
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            in_code = not in_code
            continue
        if not in_code or ARROW not in line:
            continue
        segments = [DOC_PATH.findall(segment) for segment in line.split(ARROW)]
        for left, right in zip(segments, segments[1:]):
            importer = left[-1] if left else ""
            arrows += [(number, importer, imported) for imported in right or [""]]
    return arrows


def _doc_modules(path: str, modules: dict[str, Path]) -> set[str]:
    """The modules a doc path stands for: a file is one module, a folder is every module under it."""
    if path.endswith("/"):
        package = path.rstrip("/").replace("/", ".")
        return {name for name in modules if name == package or name.startswith(package + ".")}
    name = path.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
    return {name} if name in modules else set()


def test_the_doc_reader_reads_chains_lists_and_skips_prose():
    text = "prose: `A ─► B` means A imports B\n```\nsweeps/run.py ─► sweeps/plan/trials.py, cdm/ ─► cdm/config.py\n" \
           "sweeps/*.yaml ─► sweeps/plan/spec.py\n```\n"
    assert _doc_arrows(text) == [
        (3, "sweeps/run.py", "sweeps/plan/trials.py"), (3, "sweeps/run.py", "cdm/"), (3, "cdm/", "cdm/config.py"),
        (4, "", "sweeps/plan/spec.py"),
    ]
    modules = {"cdm": ROOT, "cdm.data": ROOT, "cdm.data.views": ROOT, "cdm.config": ROOT}
    assert _doc_modules("cdm/data/", modules) == {"cdm.data", "cdm.data.views"}
    assert _doc_modules("cdm/data/views.py", modules) == {"cdm.data.views"}
    assert _doc_modules("cdm/data/__init__.py", modules) == {"cdm.data"}
    assert _doc_modules("cdm/gone.py", modules) == set()


def _doc_paths(modules: dict[str, Path]) -> set[str]:
    """How the doc writes each module: its file, or for a sub-package (``cdm/data/``) its folder."""
    files = {str(path.relative_to(ROOT)) for path in modules.values()}
    wanted = {f for f in files if not f.endswith("__init__.py")}
    return wanted | {f.removesuffix("__init__.py") for f in files if f.count("/") > 1 and f.endswith("__init__.py")}


def test_the_architecture_doc_names_every_module_and_no_module_that_is_gone():
    text = DOC.read_text()
    modules = _modules()
    named = set(DOC_PATH.findall(text))
    missing = sorted(_doc_paths(modules) - named)
    assert not missing, f"docs/ARCHITECTURE.md does not name {missing}: add each with its one job to the module map"
    gone = sorted(p for p in named if not _doc_modules(p, modules))
    assert not gone, f"docs/ARCHITECTURE.md names {gone}, which are not modules of cdm/ or sweeps/"


# A module map row: `| `path` | one job |`, or `| `path` | stage | one job |` in the sweeps/ table.
MAP_ROW = re.compile(r"^\| `((?:cdm|sweeps)/[^`]*)` \|(?: [^|`]+ \|)? (.+) \|$", re.M)
_STOP = frozenset(
    "the and or of to in on is its it by for with as at from one per each every that this which what are not no "
    "their into only once when than".split()
)
WORDS_FOUND = 0.6
"""Share of a row's words (four letters or more, not counting code) that its module's source must contain.
Every real row passes (the lowest has 0.67); of the 10,302 rows made by putting each module's description on
every other module, 11.5 % pass this and the check of names in code."""


def _map_rows(text: str) -> dict[str, str]:
    """Module map rows of the doc: module path → its one-job description."""
    return dict(MAP_ROW.findall(text))


def _source(path: str) -> str:
    """The text a row describes: a module's file, or every file of a package folder."""
    files = sorted((ROOT / path).rglob("*.py")) if path.endswith("/") else [ROOT / path]
    return "\n".join(f.read_text() for f in files)


def _description_errors(path: str, description: str, source: str) -> list[str]:
    """Why ``description`` does not describe ``source``: a name in code (`fit`, `LossTerms`, `load_config`)
    the source never writes, or too few of its words found in the source (a description of another module)."""
    errors = [f"{path}: names `{name}`, which it does not define or use"
              for name in re.findall(r"`([A-Za-z_]\w*)(?:\([^`]*\))?`", description) if name not in source]
    prose = re.sub(r"`[^`]*`", " ", description).lower()
    words = [w for w in re.findall(r"[a-z][a-z-]{3,}", prose) if w not in _STOP]
    found = sum(w in source.lower() for w in words)
    if words and found < WORDS_FOUND * len(words):
        missing = sorted({w for w in words if w not in source.lower()})
        errors.append(f"{path}: {found} of its {len(words)} words are in its source (missing: {', '.join(missing)})")
    return errors


def test_the_description_check_catches_a_description_of_another_module():
    metrics = _source("cdm/metrics.py")
    ours = "Chamfer distance and F-score as BDM's evaluation code defines them"
    diffusion = "the noise schedule, the ε/x₀/v targets, `SamplerSettings` and the DDIM/DDPM samplers"
    assert _description_errors("cdm/metrics.py", ours, metrics) == []
    assert _description_errors("cdm/metrics.py", diffusion, metrics) == [
        "cdm/metrics.py: names `SamplerSettings`, which it does not define or use",
        "cdm/metrics.py: 0 of its 6 words are in its source (missing: ddim, ddpm, noise, samplers, schedule, targets)",
    ]


def test_every_module_has_its_own_row_in_the_module_map():
    missing = sorted(_doc_paths(_modules()) - set(_map_rows(DOC.read_text())))
    assert not missing, f"docs/ARCHITECTURE.md's module map has no row for {missing}: add each with its one job"


@pytest.mark.parametrize("path", sorted(_map_rows(DOC.read_text())))
def test_each_module_map_row_describes_its_module(path):
    assert (ROOT / path).exists(), f"docs/ARCHITECTURE.md has a row for {path}, which does not exist"
    assert _description_errors(path, _map_rows(DOC.read_text())[path], _source(path)) == []


def test_every_arrow_of_the_architecture_doc_is_an_import():
    modules, graph = _modules(), _graph()
    arrows = _doc_arrows(DOC.read_text())
    assert len(arrows) > 20  # the reader found the picture
    false = []
    for number, importer, imported in arrows:
        sources, targets = _doc_modules(importer, modules), _doc_modules(imported, modules)
        if not sources or not targets or not any(graph[s] & (targets - sources) for s in sources):
            false.append(f"line {number}: {importer or '?'} {ARROW} {imported or '?'}")
    assert not false, "arrows of docs/ARCHITECTURE.md with no import behind them (A ─► B: A imports B):\n" + "\n".join(
        false
    )


STAGES = ("plan", "compare", "execute", "results")
"""``sweeps/``'s stage packages stacked from the bottom: each may import only those before it. Not the run
order (plan, execute, compare, results): ``compare/`` is plain numbers that ``execute/`` already uses while
the trials run, so ``execute/`` and ``results/`` build on it, and it on ``plan/`` (docs/ARCHITECTURE.md)."""


def _stage(module: str) -> int | None:
    """Height of a ``sweeps`` module's stage in :data:`STAGES`; None for the entry points and the
    storage modules every stage shares (``sweeps.run``, ``sweeps.report``, ``sweeps.rerun``, ``sweeps.storage``, …)."""
    parts = module.split(".")
    return STAGES.index(parts[1]) if len(parts) > 2 and parts[0] == "sweeps" and parts[1] in STAGES else None


ENTRIES = ("sweeps.run", "sweeps.report", "sweeps.rerun", "sweeps.register", "sweeps.inputs")
"""The command lines of sweeps/: they may import any stage."""


def _backward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Imports that point from a stage to one built on it, or from a shared module into any stage."""
    bad = []
    for importer, imported in graph.items():
        if not importer.startswith("sweeps.") or importer in ENTRIES:
            continue
        for target in imported:
            if not target.startswith("sweeps."):
                continue
            source, dest = _stage(importer), _stage(target)
            if dest is not None and (source is None or dest > source):
                bad.append(f"{importer} ─► {target}")
    return sorted(bad)


def test_the_stage_check_catches_an_import_of_a_stage_built_on_the_importer():
    graph = {
        "sweeps.plan.spec": {"sweeps.execute.trial"},
        "sweeps.execute.trial": {"sweeps.plan.spec", "sweeps.storage"},
        "sweeps.storage": {"sweeps.compare.table"},
        "sweeps.run": {"sweeps.results.publish"},
    }
    assert _backward_arrows(graph) == [
        "sweeps.plan.spec ─► sweeps.execute.trial",
        "sweeps.storage ─► sweeps.compare.table",
    ]


def test_sweeps_stages_import_only_the_stages_they_build_on():
    modules = _modules()
    assert {m.split(".")[1] for m in modules if _stage(m) is not None} == set(STAGES)
    assert _backward_arrows(_graph()) == []


LONG_ALLOWED = {"cdm.config"}
"""The config schema: one typed group per section, read as a reference, not top to bottom."""


def test_no_module_is_over_450_lines_but_the_config_schema():
    long = {name: n for name, path in _modules().items() if (n := len(path.read_text().splitlines())) > 450}
    assert set(long) <= LONG_ALLOWED, f"split these by job: {long}"


LONG_FUNCTION = 80
"""Lines a function of cdm/ or sweeps/ may span, its docstring included (issue 45)."""


def _long_functions(path: Path, limit: int) -> dict[str, int]:
    """Functions and methods of ``path`` spanning more than ``limit`` lines, name → lines."""
    return {
        node.name: n
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and (n := node.end_lineno - node.lineno + 1) > limit
    }


def test_the_length_check_counts_a_function_from_def_to_its_last_line(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("def short():\n    return 1\n\n\nclass A:\n    def long(self):\n" + "        x = 1\n" * 80)
    assert _long_functions(source, LONG_FUNCTION) == {"long": 81}


def test_no_function_is_over_80_lines():
    long = {
        f"{name}.{function}": n
        for name, path in _modules().items()
        for function, n in _long_functions(path, LONG_FUNCTION).items()
    }
    assert not long, f"split these into steps: {long}"


def test_the_front_door_stays_thin():
    """sweeps/run.py parses the arguments and calls one function per stage (docs/ARCHITECTURE.md): at most
    200 lines, no function over 60; a check or a step that grows it belongs to its stage."""
    run = ROOT / "sweeps" / "run.py"
    assert len(run.read_text().splitlines()) <= 200
    assert _long_functions(run, 60) == {}

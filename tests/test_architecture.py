"""One-way architecture: no import cycle in cdm/ or sweeps/, the model library knows nothing of the sweep stack
(Ray, MLflow, Optuna) or of sweeps/, sweeps/'s stages import only those they build on, modules and functions stay
short, and ``docs/ARCHITECTURE.md`` holds the import picture ``docs/architecture.py`` draws from the code now and a
walk whose every step is a real call.

Imports are read by ``docs/architecture.py`` with ``ast`` from the source, every one of them: module level, inside
functions (deferred imports) and under ``TYPE_CHECKING``, so a cycle hidden behind a lazy import counts too.
"""

from __future__ import annotations

import ast
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_SPEC = importlib.util.spec_from_file_location("docs_architecture", ROOT / "docs" / "architecture.py")
arch = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(arch)
FORBIDDEN_IN_CDM = ("ray", "mlflow", "optuna", "sweeps")
DOC = arch.DOC
DOC_BYTES = 13_000
"""The doc explains in at most a third of its length at b204d21 (41,389 bytes, issue 60); its picture is generated."""


def test_the_cycle_finder_finds_a_planted_cycle_and_accepts_a_tree():
    assert arch.cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert arch.cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_import_reader_sees_lazy_relative_and_type_checking_imports(tmp_path):
    package = tmp_path / "cdm"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from cdm import b\n"
        "def f():\n    from .c import thing\n    import cdm.d.e\n"
    )
    assert arch.imported(package / "a.py", "cdm.a", {"cdm", "cdm.a", "cdm.b", "cdm.c", "cdm.d", "cdm.d.e"}) == {
        "cdm.b",
        "cdm.c",
        "cdm.d.e",
    }


def test_no_import_cycle_in_cdm_or_sweeps():
    graph = arch.graph()
    assert len(graph) > 30 and "cdm.train" in graph and "sweeps.execute.trial" in graph  # the walk found the code
    cycle = arch.cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


@pytest.mark.parametrize("name", sorted(n for n in arch.modules() if n == "cdm" or n.startswith("cdm.")))
def test_the_model_library_does_not_import_the_sweep_stack(name):
    tree = ast.parse(arch.modules()[name].read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            roots.add(node.module.split(".")[0])
    assert not roots & set(FORBIDDEN_IN_CDM), f"{name} imports {sorted(roots & set(FORBIDDEN_IN_CDM))}"


STAGES = ("plan", "compare", "execute", "results")
"""``sweeps/``'s stage packages stacked from the bottom: each may import only those before it. Not the run
order (plan, execute, compare, results): ``compare/`` is plain numbers that ``execute/`` already uses while
the trials run, so ``execute/`` and ``results/`` build on it, and it on ``plan/`` (docs/ARCHITECTURE.md)."""


def _stage(module: str) -> int | None:
    """Height of a ``sweeps`` module's stage in :data:`STAGES`; None for the entry points and the
    storage modules every stage shares (``sweeps.run``, ``sweeps.report``, ``sweeps.rerun``, ``sweeps.store``, …)."""
    parts = module.split(".")
    return STAGES.index(parts[1]) if len(parts) > 2 and parts[0] == "sweeps" and parts[1] in STAGES else None


def _backward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Imports that point from a stage to one built on it, or from a shared module into any stage."""
    bad = []
    for importer, imported in graph.items():
        if not importer.startswith("sweeps.") or importer in arch.ENTRIES:
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
    modules = arch.modules()
    assert {m.split(".")[1] for m in modules if _stage(m) is not None} == set(STAGES)
    assert _backward_arrows(arch.graph()) == []


LONG_ALLOWED = {"cdm.config"}
"""The config schema: one typed group per section, read as a reference, not top to bottom."""


def test_no_module_is_over_450_lines_but_the_config_schema():
    long = {name: n for name, path in arch.modules().items() if (n := len(path.read_text().splitlines())) > 450}
    assert set(long) <= LONG_ALLOWED, f"split these by job: {long}"


LONG_FUNCTION = 60
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
    source.write_text("def short():\n    return 1\n\n\nclass A:\n    def long(self):\n" + "        x = 1\n" * 60)
    assert _long_functions(source, LONG_FUNCTION) == {"long": 61}


def test_no_function_is_over_60_lines():
    long = {
        f"{name}.{function}": n
        for name, path in arch.modules().items()
        for function, n in _long_functions(path, LONG_FUNCTION).items()
    }
    assert not long, f"split these into steps: {long}"


def test_the_front_door_stays_thin():
    """sweeps/run.py parses the arguments and calls one function per stage (docs/ARCHITECTURE.md): at most
    200 lines; a check or a step that grows it belongs to its stage."""
    assert len((ROOT / "sweeps" / "run.py").read_text().splitlines()) <= 200


def test_the_picture_groups_modules_into_boxes_and_draws_only_the_arrows_no_longer_path_shows(tmp_path):
    files = {
        "cdm/__init__.py": "", "cdm/config.py": "import cdm.io.files\n", "cdm/train.py": "from cdm.model import net\n",
        "cdm/io/__init__.py": "", "cdm/io/files.py": "", "cdm/io/torch/__init__.py": "",
        "cdm/io/torch/load.py": "from cdm.io import files\n", "cdm/model/__init__.py": "",
        "cdm/model/net.py": "from cdm import config\nfrom cdm.io.torch import load\n", "sweeps/__init__.py": "",
        "sweeps/run.py": "import cdm.train\n", "sweeps/storage.py": "from cdm.io.files import x\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    found, imports = arch.modules(tmp_path), arch.graph(tmp_path)
    assert arch.boxes(found, imports) == {
        "cdm": "cdm/ base", "cdm.config": "cdm/ base", "cdm.train": "cdm/ top", "cdm.io": "cdm/io/",
        "cdm.io.files": "cdm/io/", "cdm.io.torch": "cdm/io/", "cdm.io.torch.load": "cdm/io/", "cdm.model": "cdm/model/",
        "cdm.model.net": "cdm/model/", "sweeps": "sweeps/ shared", "sweeps.run": "sweeps/ commands",
        "sweeps.storage": "sweeps/ shared"}
    edges = arch.box_edges(arch.boxes(found, imports), imports)
    assert edges["cdm/model/"] == {"cdm/ base", "cdm/io/"} and edges["sweeps/ commands"] == {"cdm/ top"}
    # model → io is drawn through cdm/ base; a cycle keeps both its arrows.
    assert arch.drawn(edges)["cdm/model/"] == {"cdm/ base"}
    assert arch.drawn({"a": {"b"}, "b": {"a"}}) == {"a": {"b"}, "b": {"a"}}
    block = arch.render(tmp_path)
    assert "  cdm_model --> cdm_base\n" in block and "cdm_model --> cdm_io" not in block
    assert "| `cdm/io/` | files, torch/load | — |" in block and "| `cdm/model/` | net | cdm/ base, cdm/io/ |" in block


def test_the_writer_replaces_only_the_generated_block():
    text = f"# Doc\n\nabove\n{arch.BEGIN}\nold picture\n{arch.END}\nbelow\n"
    new = arch.with_block(text, f"{arch.BEGIN}\nnew\n{arch.END}")
    assert new == f"# Doc\n\nabove\n{arch.BEGIN}\nnew\n{arch.END}\nbelow\n"
    assert arch.doc_block(new) == f"{arch.BEGIN}\nnew\n{arch.END}"
    with pytest.raises(ValueError, match="no .* block"):
        arch.with_block("# Doc without markers\n", "x")


def test_the_architecture_doc_holds_the_picture_the_code_draws_now():
    assert arch.doc_block(DOC.read_text()) == arch.render(), (
        "docs/ARCHITECTURE.md's import picture is stale: run python docs/architecture.py --write")


def test_the_architecture_doc_explains_in_at_most_13_kb():
    size = len(DOC.read_bytes())
    assert size <= DOC_BYTES, f"docs/ARCHITECTURE.md is {size} bytes: explain in fewer words, at most {DOC_BYTES}"


DOC_PATH = re.compile(r"(?<![\w/.])((?:cdm|sweeps)/(?:[A-Za-z_]\w*/)*(?:[A-Za-z_]\w*\.py)?)(?![\w*.])")
"""A file or folder of the code as the doc's prose writes it: ``cdm/data/views.py``, ``cdm/io/``."""


def test_the_doc_names_only_files_and_folders_that_exist():
    text = DOC.read_text()
    named = set(DOC_PATH.findall(text.replace(arch.doc_block(text), "")))
    assert {"cdm/config.py", "cdm/io/", "sweeps/run.py"} <= named  # the reader found the prose's paths
    gone = sorted(p for p in named if not (ROOT / p).exists())
    assert not gone, f"docs/ARCHITECTURE.md names {gone}, which do not exist: name where the job lives"


MAX_STEPS = 15


def _function(path: Path, name: str) -> ast.AST | None:
    """The function ``name`` (``f``, or ``Class.method``; a bare name also finds a method) defined in ``path``."""
    owner, _, leaf = name.rpartition(".")
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ClassDef) and owner in ("", node.name):
            found = [f for f in node.body if isinstance(f, ast.FunctionDef) and f.name == leaf]
            if found:
                return found[0]
        elif isinstance(node, ast.FunctionDef) and not owner and node.name == leaf:
            return node
    return None


def _names(function: ast.AST) -> set[str]:
    """Every name ``function`` calls or hands on: ``f(…)``, ``obj.f(…)``, ``partial(f, …)``, ``Tune(f)``."""
    return {n.id if isinstance(n, ast.Name) else n.attr
            for n in ast.walk(function) if isinstance(n, ast.Name | ast.Attribute)}


def _step_errors(root: Path, caller_file: str, caller: str, through: list[str], callee_file: str,
                 callee: str) -> list[str]:
    """Why a step is not a chain of real calls: a function that is not defined where the doc says, or one of the
    chain ``caller → through… → callee`` that does not call (or hand to Ray) the next. Helpers are looked up in
    the caller's file, then the callee's."""
    chain = [(caller_file, caller), *[(caller_file if _function(root / caller_file, t) else callee_file, t)
                                      for t in through], (callee_file, callee)]
    errors, nodes = [], []
    for file, name in chain:
        node = _function(root / file, name) if (root / file).is_file() else None
        if node is None:
            errors.append(f"{file}:{name} is not defined")
        nodes.append(node)
    for (file, name), node, (_, nxt) in zip(chain, nodes, chain[1:]):
        if node is not None and nxt.rpartition(".")[2] not in _names(node):
            errors.append(f"{file}:{name} does not call {nxt}")
    return errors


def test_the_walk_check_catches_a_step_that_is_no_call(tmp_path):
    (tmp_path / "a.py").write_text("def main():\n    _go(1)\n\n\ndef _go(x):\n    b.Trainer().fit(x)\n")
    (tmp_path / "b.py").write_text("class Trainer:\n    def fit(self, x):\n        pass\n")
    assert _step_errors(tmp_path, "a.py", "main", ["_go"], "b.py", "Trainer.fit") == []
    assert _step_errors(tmp_path, "a.py", "main", [], "b.py", "Trainer.fit") == ["a.py:main does not call Trainer.fit"]
    assert _step_errors(tmp_path, "a.py", "_go", [], "b.py", "Trainer.gone") == [
        "b.py:Trainer.gone is not defined", "a.py:_go does not call Trainer.gone"]
    text = "## The walk of one hyperparameter\n\n1. `a.py:main` → `b.py:Trainer.fit` (through `_go`): it trains.\n"
    assert arch.walk_steps(text) == [("a.py", "main", ["_go"], "b.py", "Trainer.fit")]


def test_each_step_of_the_walk_is_a_real_call_from_the_front_door_on():
    steps = arch.walk_steps(DOC.read_text())
    assert 0 < len(steps) <= MAX_STEPS
    assert steps[0][:2] == ("sweeps/run.py", "main")
    reached = {("sweeps/run.py", "main")}
    for caller_file, caller, _, callee_file, callee in steps:
        assert (caller_file, caller) in reached, f"the walk leaves from {caller_file}:{caller}, which it never reached"
        reached.add((callee_file, callee))
    errors = [e for step in steps for e in _step_errors(ROOT, *step)]
    assert not errors, "docs/ARCHITECTURE.md's walk:\n" + "\n".join(errors)

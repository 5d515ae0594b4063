"""Comparing a finished sweep, end to end: one real smoke sweep (Ray, MLflow SQLite) serves every test.

What MLflow holds after the runner (tags, final metrics, panels, the parent's table and plots), the
report rebuilt from it, ``notebooks/compare.ipynb`` executed headlessly, and the MLflow UI in headless
Chromium (Debian's ``chromium``; ``.ci/run`` installs it). ``CDM_UPDATE_SCREENSHOTS=1`` also writes
the UI screenshots the README shows into ``docs/``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import nbformat
import numpy as np
import pytest
from mlflow import MlflowClient
from mlflow.entities import Run
from nbclient import NotebookClient

from docs import screenshots
from sweeps import run
from sweeps.results import publish
from sweeps.store.read import last_eval_files, last_objects
from tests.integration.local_ray import local_ray
from tests.test_publish import _overlap, panel_views

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]

# eval.save_clouds 2: the smoke profile evaluates one object of each of its 2 categories; draw both.
SPEC = """name: compare
paper:
  table: Table 5
  note: Co3D teddybear, F1@0.01
  rows:
    - {label: "10 frames + 0.02 point size", when: {priors.point_size: 0.02}, values: {eval/f1: 0.451, eval/cd: 101.5}}
    - {label: "10 frames + 0.04 point size", when: {priors.point_size: 0.04}, values: {eval/f1: 0.461, eval/cd: 99.2}}
grid: {priors.point_size: [0.02, 0.04]}
profiles: {smoke: {overrides: {eval.save_clouds: 2}}}
"""
PAPER = {"point_size=0.02": (0.451, 101.5), "point_size=0.04": (0.461, 99.2)}


@dataclass(frozen=True)
class Smoke:
    uri: str
    folder: Path
    experiment_id: str
    parent: Run
    children: list[Run]


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> Smoke:
    folder = tmp_path_factory.mktemp("compare")
    (folder / "spec.yaml").write_text(SPEC)
    uri = f"sqlite:///{folder}/mlflow.db"
    with local_ray():  # shut down after the sweep: the notebook and the browser need the CPUs
        argv = [str(folder / "spec.yaml"), "--smoke", "--out", str(folder / "results"), "--tracking-uri", uri]
        assert run.main(argv) == 0
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("compare")
    runs = client.search_runs([exp.experiment_id])
    parent = next(r for r in runs if r.data.tags.get("kind") == "sweep")
    children = sorted((r for r in runs if "mlflow.parentRunId" in r.data.tags), key=lambda r: r.info.run_name)
    return Smoke(uri, folder, exp.experiment_id, parent, children)


def test_children_carry_swept_values_final_metrics_and_a_panel_per_object(smoke):
    client = MlflowClient(smoke.uri)
    assert [c.info.run_name for c in smoke.children] == ["point_size=0.02 · seed 0", "point_size=0.04 · seed 0"]
    for child in smoke.children:
        tags, metrics = child.data.tags, child.data.metrics
        assert (tags["cell"], tags["seed"], tags["spec"]) == (child.info.run_name.split(" · ")[0], "0", "compare")
        assert tags["category"] == tags["categories"] == "chair,airplane"
        assert child.data.params["priors.point_size"] == tags["cell"].removeprefix("point_size=")
        for name in ("cd", "f1"):
            assert metrics[f"final/{name}"] == metrics[f"eval/{name}"]  # both the trial's own float
        assert {m.step for m in client.get_metric_history(child.info.run_id, "final/f1")} == {20}
        files = last_eval_files(client, child.info.run_id)
        objects = last_objects(client, child.info.run_id)
        assert len(objects) == 2
        # Per category a single value, the metric final/<metric>/<category>: here the one object each category
        # scored, so the very score objects.csv holds for it (the trainer writes both from one float).
        for row in objects:
            category = str(row["category"])
            for name in ("cd", "f1"):
                assert metrics[f"final/{name}/{category}"] == pytest.approx(float(row[name]), rel=1e-12)
                assert f"eval/{name}/{category}" not in metrics and f"final/{name}/{category}" not in child.data.params
        # One-point series: the final scores, overall and per category, the swept value and a lone evaluation.
        single = [k for k in metrics if len(client.get_metric_history(child.info.run_id, k)) == 1]
        assert set(single) <= {"final/cd", "final/f1", "swept/priors.point_size", "eval/cd", "eval/f1",
                               *(f"final/{m}/{c}" for m in ("cd", "f1") for c in ("chair", "airplane"))}, single
        # MLflow's own source tags, the evaluation set as a dataset input, MLflow's system metrics.
        assert child.data.tags["mlflow.source.git.commit"] == child.data.tags["repro.git_commit"]
        (used,) = client.get_run(child.info.run_id).inputs.dataset_inputs
        assert used.dataset.digest == child.data.tags["eval_set"] == objects[0]["eval_set"]
        for row in objects:
            name = str(row["object_id"]).replace("/", "_")
            png = f"eval/step_0000020/panels/{name}.png"
            assert png in files and f"eval/step_0000020/clouds/{name}.ply" in files
            png = client.download_artifacts(child.info.run_id, png, tempfile.mkdtemp(dir=smoke.folder))
            views = panel_views(Path(png))
            assert all(v.sum() > 30 for v in views)  # every view draws a cloud
            # 20 smoke steps reconstruct poorly (CD ×1000 ≫ 0: 45 measured in the data sets' fixed frames): the
            # prediction views must not redraw the GT's.
            assert row["cd"] > 20 and max(_overlap(views[k], views[3 + k]) for k in range(3)) < 0.8
    parent_files = {a.path for a in client.list_artifacts(smoke.parent.info.run_id)}
    parent_files |= {a.path for a in client.list_artifacts(smoke.parent.info.run_id, "plots")}
    parent_files |= {a.path for a in client.list_artifacts(smoke.parent.info.run_id, "reconstructions")}
    assert parent_files >= {
        "results.md",
        "results.csv",
        "spec.yaml",
        "plan.json",
        "plots/metric_vs_value.png",
        "plots/training_curves.png",
        "reconstructions/reconstructions.png",
        "reconstructions/reconstructions.html",
    }
    # The parent carries the results: per cell and per baseline, under readable names, and a description.
    parent = client.get_run(smoke.parent.info.run_id)
    # The parent: the baselines' scores, overall and per category, as metrics; the cells' results in results.md.
    assert sorted(parent.data.metrics) == sorted(
        f"baseline/{b}/{m}{c}" for b in ("sphere", "gaussian", "category_mean", "retrieval") for m in ("cd", "f1")
        for c in ("", "/chair", "/airplane")
    )
    assert parent.data.metrics["baseline/sphere/f1/chair"] >= 0
    for child in smoke.children:
        assert not [k for k in child.data.metrics if k.startswith("baseline/")]  # once, on the parent
        assert "train.out_dir" not in child.data.params
    assert {f"baseline/{b}/f1" for b in ("sphere", "gaussian", "category_mean", "retrieval")} <= set(
        parent.data.metrics
    )
    description = parent.data.tags["mlflow.note.content"]
    # The headline leads: a best cell only where the leader is apart from the next one, as the smoke outcome falls.
    head = " ".join(description.split("\n\n")[0].split())
    assert description.startswith("**compare**") and "Profile **smoke**" in description
    assert (
        "best cell point_size=0.0" in head or "no cell is resolvably best by eval/f1: the leader point_size=0.0" in head
    )
    assert parent.info.run_name.startswith("compare · smoke: ") and parent.info.run_name.split(": ", 1)[1] in head
    assert client.get_experiment(smoke.experiment_id).tags["mlflow.experimentKind"] == "custom_model_development"
    assert "| cell | eval/f1 | eval/cd | Δf1 vs point_size=0.02 [95% CI] | verdict |" in description
    assert max(len(line) for line in description.splitlines()) <= 200 and not re.findall(r"\d\.\d{5,}", description)
    for child in smoke.children:  # each child explains itself and links its sweep
        note = " ".join(client.get_run(child.info.run_id).data.tags["mlflow.note.content"].split())
        assert note.startswith(f"**{child.data.tags['cell']}**, seed 0") and smoke.parent.info.run_id in note
        artifacts = {a.path for a in client.list_artifacts(child.info.run_id)}
        assert artifacts == {"config.yaml", "curves", "environment", "eval"}  # the weights: the run's MLflow model
        models = client.search_logged_models([smoke.experiment_id])
        assert [m.name for m in models if m.source_run_id == child.info.run_id] == ["model"]


def test_report_rebuilds_the_runners_table_from_mlflow(smoke, tmp_path, capsys, monkeypatch):
    out = tmp_path / "report"
    assert publish.main(["compare", "--tracking-uri", smoke.uri, "--out", str(out)]) == 0
    rebuilt = (out / "results.md").read_text()
    runner = smoke.folder / "results" / "compare" / "smoke"
    assert rebuilt == (runner / "results.md").read_text()
    # results.csv byte for byte: MLflow holds the very floats the runner's table was made of.
    ours, theirs = (out / "results.csv").read_bytes(), (runner / "results.csv").read_bytes()
    assert hashlib.md5(ours).hexdigest() == hashlib.md5(theirs).hexdigest(), (ours.decode(), theirs.decode())
    assert re.search(rb",\d+\.\d{6,}", ours)  # full precision: more digits than the printed table's
    assert "Δf1 vs point_size=0.02 [95% CI]" in rebuilt and rebuilt.count("| point_size=0.0") == 2
    capsys.readouterr()
    monkeypatch.chdir(tmp_path)  # the default --out is results/<experiment>/report under the working directory
    assert publish.main(["compare", "--tracking-uri", smoke.uri]) == 0
    assert (tmp_path / "results" / "compare" / "report" / "results.md").read_text() == rebuilt
    assert "compare — profile smoke" in capsys.readouterr().out


def test_notebook_runs_top_to_bottom_and_shows_the_paper_layout(smoke, tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", smoke.uri)
    monkeypatch.setenv("CDM_EXPERIMENT", "compare")
    monkeypatch.setenv("CDM_COMPARE_OUT", str(tmp_path / "out"))
    nb = nbformat.read(ROOT / "notebooks" / "compare.ipynb", as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell('print(table.to_json(orient="split"))'))
    NotebookClient(
        nb, timeout=180, kernel_name="python3", resources={"metadata": {"path": str(ROOT / "notebooks")}}
    ).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    table = json.loads(nb.cells[-1].outputs[0]["text"])
    columns = [tuple(c) for c in table["columns"]]
    assert table["index"] == ["point_size=0.02", "point_size=0.04"]  # one row per cell
    by_name = {c.data.tags["cell"]: c.data.metrics for c in smoke.children}
    for cell, row in zip(table["index"], table["data"]):
        value = dict(zip(columns, row))
        assert value[("all", "F1 ours")] == pytest.approx(by_name[cell]["eval/f1"])
        assert value[("all", "CD ours")] == pytest.approx(by_name[cell]["eval/cd"])
        assert (value[("all", "F1 paper")], value[("all", "CD paper")]) == PAPER[cell]
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]
    assert len(images) == 2 + 4  # two plots, then 2 panels for each of the 2 trials


@pytest.fixture
def mlflow_server(smoke, tmp_path):
    """``mlflow server`` on the smoke store, bound to 127.0.0.1; stopped (its whole process group) also on failure."""
    with screenshots.mlflow_server(smoke.uri, tmp_path / "server.log") as url:
        yield url


def _keep(screenshot: Path, name: str) -> None:
    """With CDM_UPDATE_SCREENSHOTS=1, a downscaled copy for the README (docs/); ``docs/screenshots.py``
    takes the same pictures from any store (the main job's)."""
    if os.environ.get("CDM_UPDATE_SCREENSHOTS") == "1":
        screenshots.shrink(screenshot, ROOT / "docs" / name)


@pytest.fixture(scope="module")  # module scope: checked before the module's smoke sweep, so a skip costs nothing
def chromium() -> str:
    found = shutil.which("chromium")
    if found is None:
        pytest.skip("Debian's chromium is not installed and .ci/run could not install it (apt-get install chromium)")
    return found


def test_mlflow_opens_model_training_with_the_answer_on_the_first_screen(chromium, smoke, mlflow_server, tmp_path):
    """A first visit (fresh Chromium profile, 1,280 × 800, MLflow's default panels: the Assistant open) of the
    links the runner prints: the model-training workflow, and on the first screen the answer."""
    client = MlflowClient(smoke.uri)
    rows = client.search_runs([smoke.experiment_id], f"tags.sweep = '{smoke.parent.info.run_id}'")  # the view's rows
    baselines = sorted(r.info.run_name for r in rows if r.data.tags.get("kind") == "baseline")
    assert baselines == [f"baseline: {b}" for b in ("category_mean", "gaussian", "retrieval", "sphere")]
    tags = {c.data.tags["cell"]: client.get_run(c.info.run_id).data.tags for c in smoke.children}
    assert tags["point_size=0.02"]["vs reference"] == "reference"
    versus = tags["point_size=0.04"]["vs reference"]  # e.g. "unclear [-0.033, +0.064] Δf1 +0.016"
    verdict, interval = re.fullmatch(
        r"(unclear|better|worse|[a-z ,]+ on (?:f1|cd)) (\[[-+]\d\.\d{3}, [-+]\d\.\d{3}\]) Δf1 [-+]\d\.\d{3}", versus
    ).groups()
    urls = screenshots.pages(
        mlflow_server, smoke.experiment_id, smoke.parent.info.run_id, [c.info.run_id for c in smoke.children]
    )
    assert all("workflowType=machine_learning" in u for u in urls.values())
    # The printed link: a verdict word, its interval, the baselines as rows; no GenAI navigation.
    wanted = [
        verdict,
        interval,
        "reference",
        "baseline: sphere",
        "baseline: gaussian",
        "final/f1",
        "final/cd",
        "Model registry",
    ]
    runs_png = tmp_path / "runs.png"
    seen = screenshots.first_screen(
        chromium,
        urls["mlflow_sweep_view.png"],
        wanted + list(screenshots.GENAI_ENTRIES),
        runs_png,
        tmp_path / "profile-runs",
        wait_for=wanted,
    )
    assert seen == {t: t in wanted for t in seen}, seen
    # The parent run: its name, on top of the page, is the verdict.
    parent = client.get_run(smoke.parent.info.run_id)
    parent_png = tmp_path / "parent.png"
    seen = screenshots.first_screen(
        chromium,
        urls["mlflow_parent_run.png"],
        [parent.info.run_name, "Model registry"],
        parent_png,
        tmp_path / "profile-parent",
    )
    assert seen == {parent.info.run_name: True, "Model registry": True}
    assert "resolvably best" in parent.info.run_name or "best cell" in parent.info.run_name
    child_png = tmp_path / "child.png"
    name = smoke.children[0].info.run_name
    assert screenshots.first_screen(
        chromium, urls["mlflow_child_run.png"], [name], child_png, tmp_path / "profile-child"
    ) == {name: True}
    compare_png = tmp_path / "compare.png"
    dom = screenshots.chromium_page(chromium, urls["mlflow_compare.png"], compare_png, tmp_path / "profile-compare")
    assert "Comparing 2 Runs" in dom
    for child in smoke.children:
        assert child.info.run_name in dom and child.info.run_id in dom
    assert "priors.point_size 0.02 0.04" in _text(dom)  # the params table: one column per run
    for png in (runs_png, compare_png, parent_png, child_png):
        assert png.stat().st_size > 20_000  # a rendered page, not a blank one
    _keep(runs_png, "mlflow_sweep_view.png")
    _keep(compare_png, "mlflow_compare.png")
    _keep(parent_png, "mlflow_parent_run.png")
    _keep(child_png, "mlflow_child_run.png")


def test_reconstruction_viewer_draws_its_canvases_offline(chromium, smoke, tmp_path):
    client = MlflowClient(smoke.uri)
    page = Path(
        client.download_artifacts(smoke.parent.info.run_id, "reconstructions/reconstructions.html", str(tmp_path))
    )
    shot = tmp_path / "viewer.png"
    dom = screenshots.chromium_page(chromium, page.as_uri(), shot, tmp_path, 1600, 700)
    # One canvas per column (2 cells, ground truth, best baseline), created and drawn by the inline script,
    # each titled with that object's CD and F1 in it (none under the ground truth).
    assert dom.count("<canvas") == 4 and "ground truth" in dom and "baseline: " in dom
    rows = last_objects(MlflowClient(smoke.uri), smoke.children[0].info.run_id)
    assert any(f"CD {r['cd']:.2f} · F1 {r['f1']:.3f}" in _text(dom) for r in rows)  # the shown object's own scores
    assert len(re.findall(r"CD \d+\.\d\d · F1 \d\.\d{3}", _text(dom))) == 3
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    blue = ((np.abs(pixels - [31, 119, 180]).max(axis=2) < 60) & (pixels[..., 2] > pixels[..., 0] + 60)).sum()
    assert blue > 200  # the cells' clouds are drawn, not only the empty canvases
    _keep(shot, "reconstructions_viewer.png")


def _text(html: str) -> str:
    """The page's visible text, whitespace collapsed (tags dropped)."""
    return " ".join(
        re.sub(r"<[^>]+>", " ", re.sub(r"<(script|style)[^>]*>.*?</\1>", "", html, flags=re.DOTALL)).split()
    )

"""Smoke run of sweeps/bdm_blend.yaml on a real local Ray cluster and MLflow store.

The spec is read from the repository and only its category axis is cut to two categories (8 trials
instead of 20, ~30 s on 2 CPUs); everything else — cells, paper rows, auto priors — is the file's.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import yaml
from mlflow import MlflowClient

from cdm.checkpoint import CHECKPOINT_FILE, load_checkpoint
from sweeps import run

pytestmark = [pytest.mark.ray, pytest.mark.slow]

SPEC = Path(__file__).resolve().parents[2] / "sweeps" / "bdm_blend.yaml"


def test_bdm_blend_smoke_sweep(cluster, tmp_path, capsys):
    tree = yaml.safe_load(SPEC.read_text())
    tree["grid"]["data.categories"] = [["airplane"], ["chair"]]
    spec = tmp_path / "bdm_blend.yaml"
    spec.write_text(yaml.safe_dump(tree, allow_unicode=True))
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert run.main([str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri]) == 0
    out = capsys.readouterr().out

    sweep = tmp_path / "results" / "bdm_blend" / "smoke"
    with (sweep / "results.csv").open() as fh:
        rows = {r["cell"]: r for r in csv.DictReader(fh)}
    settings = ("PC²", "PC²+BDM", "CDM", "CDM+BDM")
    cells = [f"{s} · categories={c}" for s in settings for c in ("airplane", "chair")]
    assert [c.removesuffix(" ★") for c in rows if not c.startswith("baseline")] == cells
    # Every row sits beside its Table 2 numbers (airplane / chair columns of the paper).
    paper = {
        (r["cell"].removesuffix(" ★"), float(r["eval/cd paper"]), float(r["eval/f1 paper"]))
        for r in rows.values()
        if r["eval/cd paper"]
    }
    assert paper == {
        ("PC² · categories=airplane", 65.97, 0.655), ("PC² · categories=chair", 65.57, 0.464),
        ("PC²+BDM · categories=airplane", 59.04, 0.660), ("PC²+BDM · categories=chair", 64.21, 0.485),
        ("CDM · categories=airplane", 59.72, 0.660), ("CDM · categories=chair", 62.93, 0.476),
        ("CDM+BDM · categories=airplane", 57.35, 0.665), ("CDM+BDM · categories=chair", 58.54, 0.497),
    }
    assert all(
        r["ok"] == "1" and 0.0 < float(r["eval/cd mean"]) for c, r in rows.items() if not c.startswith("baseline")
    )
    assert "PC²+BDM, airplane" in out and "59.04" in out

    # One prior per category, trained by the first blended trial and reused by the second.
    priors = sorted(p.parent.name.split("-")[0] for p in (sweep / "priors").glob(f"*/{CHECKPOINT_FILE}"))
    assert priors == ["airplane", "chair"]
    assert out.count("category prior airplane: trained") == 1 and out.count("category prior airplane: reusing") == 1
    chair = next(p for p in (sweep / "priors").glob("chair-*") if p.is_dir())
    prior = load_checkpoint(chair)
    assert prior.category == "chair" and prior.config["diffusion"]["beta_end"] == 0.02

    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("bdm_blend").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    params = {c.info.run_name: c.data.params for c in children}
    assert len(params) == 8
    blended = params["PC²+BDM · categories=chair · seed 0"]
    assert blended["sampling.blend.enabled"] == "True"
    assert blended["sampling.blend.prior_checkpoint"] == str(
        sweep / "priors" / chair.name.replace("chair-", "{category}-")
    )
    assert params["PC² · categories=chair · seed 0"]["sampling.blend.prior_checkpoint"] == "auto"
    # Blending changes sampling only: the two cells of a setting train the same model.
    loss = {name: client.get_metric_history(c.info.run_id, "train/loss")[-1].value
            for c in children for name in [c.info.run_name] if "chair" in name}
    assert loss["PC² · categories=chair · seed 0"] == loss["PC²+BDM · categories=chair · seed 0"]
    assert float(rows["PC² · categories=chair"]["eval/cd mean"]) != float(
        rows["PC²+BDM · categories=chair"]["eval/cd mean"]
    )

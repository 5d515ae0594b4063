"""Chamfer/F1 against a scipy cKDTree reference of the same definitions (NOTES §4)."""

import inspect
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from cdm.config import F1_THRESHOLD, EvalConfig
from cdm.metric_names import f1_at, f1_unit
from cdm.metrics import chamfer_f1, nearest_sq_dist
from sweeps.plan.references import record

ROOT = Path(__file__).resolve().parent.parent


def reference(pred: np.ndarray, gt: np.ndarray, tau: float) -> tuple[float, float, float, float]:
    pred = pred - pred.mean(0)
    gt = gt - gt.mean(0)
    d_pred = cKDTree(gt).query(pred)[0] ** 2
    d_gt = cKDTree(pred).query(gt)[0] ** 2
    p = float((d_pred < tau).mean())
    r = float((d_gt < tau).mean())
    f1 = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return 1000.0 * (d_pred.mean() + d_gt.mean()), f1, p, r


@pytest.mark.parametrize("search", ["brute", "kdtree"])
@pytest.mark.parametrize("n,m", [(500, 500), (300, 700), (1, 50)])
def test_matches_scipy_on_random_clouds(n, m, search):
    g = torch.Generator().manual_seed(n + m)
    pred = torch.rand(3, n, 3, generator=g, dtype=torch.float64) * 0.6
    gt = torch.rand(3, m, 3, generator=g, dtype=torch.float64) * 0.6 + 0.05
    out = chamfer_f1(pred, gt, threshold=0.01, chunk=128, search=search)
    for b in range(3):
        cd, f1, p, r = reference(pred[b].numpy(), gt[b].numpy(), 0.01)
        assert abs(out.cd[b].item() - cd) <= 1e-5 * max(1.0, cd)
        assert out.f1[b].item() == pytest.approx(f1, abs=1e-5)
        assert out.precision[b].item() == pytest.approx(p, abs=1e-5)
        assert out.recall[b].item() == pytest.approx(r, abs=1e-5)


@pytest.mark.parametrize("search", ["brute", "kdtree"])
def test_float32_values_match_scipy_to_rounding(search):
    g = torch.Generator().manual_seed(0)
    pred = torch.randn(2, 2000, 3, generator=g) * 0.3
    gt = torch.randn(2, 1500, 3, generator=g) * 0.3
    out = chamfer_f1(pred, gt, search=search)
    for b in range(2):
        cd, f1, _, _ = reference(pred[b].double().numpy(), gt[b].double().numpy(), 0.01)
        assert out.cd[b].item() == pytest.approx(cd, rel=1e-5)
        assert out.f1[b].item() == pytest.approx(f1, abs=1e-3)


def test_identical_clouds_and_translation_invariance():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, 256, 3, generator=g)
    same = chamfer_f1(x, x + torch.tensor([0.5, -2.0, 1.0]))  # centring removes the shift
    assert same.cd.item() == pytest.approx(0.0, abs=1e-4)
    assert same.f1.item() == 1.0


def test_known_golden_value():
    # Two single points after centring coincide; add a second point to make the distance known.
    pred = torch.tensor([[[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]]])
    gt = torch.tensor([[[0.0, 0.0, 0.0], [0.4, 0.0, 0.0]]])
    # centred: pred {-0.1, 0.1}, gt {-0.2, 0.2}: every NN squared distance is 0.01.
    out = chamfer_f1(pred, gt, threshold=0.011)
    assert out.cd.item() == pytest.approx(20.0, rel=1e-5)
    assert out.f1.item() == 1.0
    assert chamfer_f1(pred, gt, threshold=0.009).f1.item() == 0.0


def test_nearest_sq_dist_chunking_and_search_agree():
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(2, 333, 3, generator=g), torch.rand(2, 444, 3, generator=g)
    small = nearest_sq_dist(a, b, chunk=7, search="brute")
    assert torch.allclose(small, nearest_sq_dist(a, b, chunk=4096, search="brute"))
    assert torch.allclose(small, nearest_sq_dist(a, b, search="kdtree"), atol=1e-7)


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        chamfer_f1(torch.zeros(10, 3), torch.zeros(10, 3))


def test_the_f1_threshold_has_one_home_read_by_the_metric_the_config_the_records_and_the_labels():
    assert inspect.signature(chamfer_f1).parameters["threshold"].default is F1_THRESHOLD
    assert EvalConfig.model_fields["f1_threshold"].default is F1_THRESHOLD
    assert record(None, "co3d")["eval.f1_threshold"].value == F1_THRESHOLD == 0.01
    assert f1_at(F1_THRESHOLD) == "F1@0.01 sq. dist = 0.1 world" and "within 0.1 in world units" in f1_unit(0.01)
    # The paper's value is written once: not as a threshold in the metric, the records or the labels.
    readers = ["cdm/metrics.py", "cdm/evaluate.py", "sweeps/plan/references.py", "sweeps/compare/rules.py",
               "sweeps/compare/gallery.py"]
    pattern = r"F1@0\.01|F-Score@0\.01|threshold: float = 0\.01|Stated\(0\.01|τ = 0\.01"
    written = [(f, line) for f in readers for line in (ROOT / f).read_text().splitlines() if re.search(pattern, line)]
    assert written == []

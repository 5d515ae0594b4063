"""Cells and baselines paired with the reference cell on the same objects: Δ, verdicts, beaten baselines."""

from __future__ import annotations

import pytest

from sweeps.compare.bootstrap import PairedDifference
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.pairing import Pairing, lead_difference, paired_record

SHOWN = ["eval/f1", "eval/cd"]


def _cell(name: str, f1: list[float], cd: list[float], objects: str = "abcd") -> list[TrialOutcome]:
    rows = tuple(
        {"object_id": o, "category": "chair", "f1": f, "cd": c, "baseline/sphere/f1": 0.1, "baseline/sphere/cd": 90.0}
        for o, f, c in zip(objects, f1, cd)
    )
    return [TrialOutcome(f"{name} · seed 0", name, "ok", {"eval/f1": sum(f1) / len(f1)}, objects=rows)]


def test_a_cell_better_on_every_object_is_better_and_beats_the_baseline():
    cells = {
        "ref": _cell("ref", [0.4, 0.5, 0.6, 0.5], [50.0, 40.0, 30.0, 40.0]),
        "up": _cell("up", [0.5, 0.6, 0.7, 0.6], [50.0, 40.0, 30.0, 40.0]),  # +0.1 F1 on each object, same CD
    }
    pairing = Pairing.build(cells, "ref", SHOWN, "max", ["sphere"], {})
    diff = pairing.diffs[("up", "eval/f1")]
    assert isinstance(diff, PairedDifference) and diff.n == 4
    assert (diff.mean, diff.low, diff.high) == pytest.approx((0.1, 0.1, 0.1))
    assert pairing.diffs[("up", "eval/cd")].mean == pytest.approx(0.0)
    assert pairing.verdicts == {"up": "better"}
    assert pairing.beats("up") == ["sphere"] and pairing.beats("ref") == ["sphere"]
    assert pairing.columns("ref", SHOWN, "eval/f1")[:2] == ["reference", "reference"]
    record = paired_record(pairing, "up", SHOWN, "eval/f1")
    assert record["eval/f1 delta"] == pytest.approx(0.1) and record["eval/f1 delta covers"] == "objects"
    assert (record["verdict"], record["beats baselines"]) == ("better", "sphere")
    lead = lead_difference(cells, "up", "ref", "eval/f1")
    assert lead.diff.mean == pytest.approx(0.1) and (lead.verdict, lead.covers) == ("better", "objects")


def test_the_partner_metric_names_itself_when_it_disagrees():
    cells = {
        "ref": _cell("ref", [0.4, 0.5, 0.6, 0.5], [50.0, 40.0, 30.0, 40.0]),
        "wide": _cell("wide", [0.4, 0.5, 0.6, 0.5], [60.0, 50.0, 40.0, 50.0]),  # same F1, CD +10 on each object
    }
    pairing = Pairing.build(cells, "ref", SHOWN, "max", [], {})
    assert pairing.verdicts == {"wide": "worse on cd"}


def test_a_cell_scored_on_other_objects_is_not_paired_and_a_note_says_why():
    cells = {
        "ref": _cell("ref", [0.4, 0.5, 0.6, 0.5], [50.0, 40.0, 30.0, 40.0]),
        "other": _cell("other", [0.4, 0.5, 0.6, 0.5], [50.0, 40.0, 30.0, 40.0], objects="wxyz"),
    }
    pairing = Pairing.build(cells, "ref", SHOWN, "max", [], {})
    assert pairing.diffs[("other", "eval/f1")] == "not paired" and "other" not in pairing.verdicts
    assert len(pairing.notes) == 1
    assert pairing.notes[0].startswith("not paired with ref") and pairing.notes[0].endswith(": other")
    assert lead_difference(cells, "other", "ref", "eval/f1") is None

"""Which errored trials a ``--resume`` retries, and the per-trial count it keeps in the sweep folder."""

from __future__ import annotations

import pytest

from sweeps.execute.resume_retries import RECORD, plan_retries, read_spent
from sweeps.store.files import StoreError


def test_each_errored_trial_is_retried_until_it_has_spent_max_retries():
    first = plan_retries(["b", "a"], {}, max_retries=2)
    assert first.retried == ["a", "b"] and first.given_up == [] and first.spent == {"a": 1, "b": 1}
    # "a" finished on its retry; "b" failed again, and "c" failed for the first time meanwhile
    second = plan_retries(["b", "c"], first.spent, max_retries=2)
    assert second.retried == ["b", "c"] and second.spent == {"a": 1, "b": 2, "c": 1}
    third = plan_retries(["b", "c"], second.spent, max_retries=2)
    assert third.retried == ["c"] and third.given_up == ["b"] and third.spent == {"a": 1, "b": 2, "c": 2}


def test_max_retries_zero_retries_nothing():
    none = plan_retries(["a"], {}, max_retries=0)
    assert none.retried == [] and none.given_up == ["a"] and none.spent == {}


def test_the_record_is_read_back_and_a_damaged_one_is_refused_by_name(tmp_path):
    assert read_spent(str(tmp_path)) == {}
    (tmp_path / RECORD).write_text('{"8e1f2_00000": 1}')
    assert read_spent(str(tmp_path)) == {"8e1f2_00000": 1}
    for bad in ('{"8e1f2_00000": -1}', '["8e1f2_00000"]', '{"8e1f2_00000": "1"}'):
        (tmp_path / RECORD).write_text(bad)
        with pytest.raises(StoreError, match=f"{RECORD} is not a count of retries per trial"):
            read_spent(str(tmp_path))

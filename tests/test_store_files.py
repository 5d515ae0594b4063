"""Where a sweep keeps its files: locations as the sweep's storage spells them."""

from __future__ import annotations

import pytest

from sweeps.store.files import storage_location


@pytest.mark.parametrize("sweep_dir,fs_path,location", [
    ("/data/results/ps/local", "/data/results/ps/local/trial_1/checkpoint_000001",
     "/data/results/ps/local/trial_1/checkpoint_000001"),
    ("s3://bucket/sweeps/ps/paper", "bucket/sweeps/ps/paper/trial_1/checkpoint_000003",
     "s3://bucket/sweeps/ps/paper/trial_1/checkpoint_000003"),
    ("file:///mnt/shared/ps/local", "/mnt/shared/ps/local/train/trial_2/checkpoint_2026-12-06_06-00-00.000000",
     "file:///mnt/shared/ps/local/train/trial_2/checkpoint_2026-12-06_06-00-00.000000"),
])
def test_a_ray_storage_path_is_written_as_the_sweeps_storage_spells_it(sweep_dir, fs_path, location):
    # Ray's Checkpoint.path is the storage file system's path: a URI's scheme (and query) stripped by pyarrow.
    assert storage_location(sweep_dir, fs_path) == location

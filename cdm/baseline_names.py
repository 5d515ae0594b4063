"""The names of the trivial baselines an evaluation scores beside the model, weakest first.

Apart from :mod:`cdm.evaluate` (torch and the model), so that readers of finished numbers (the results
table, the report) name the baselines without importing either.
"""

from __future__ import annotations

__all__ = ["BASELINES"]

BASELINES = ("sphere", "gaussian", "category_mean", "retrieval")
"""A sphere of the object's mean radius, a Gaussian of its per-axis spread, its category's mean cloud, and
the cloud of the training image nearest the input (:mod:`cdm.evaluate`); metrics ``baseline/<name>/…``."""

"""Units the metrics see: the data sets' own box units, or the reference code's (``eval.normalise``).

Every data set hands out clouds normalised per shape, ``x_box = (x − c)·s`` (bounding-box centre ``c``,
``s`` = 1 / largest half-extent, :class:`cdm.data.cache.ObjectRecord` ``scale``). The metrics centre
each cloud on its own mean (:mod:`cdm.metrics`), so changing units is one factor ``f`` per object,
applied to prediction and ground truth alike: ``x_scored = f · x_box``.

- ``box`` (every kind): ``f = 1``.
- ``reference`` on ``shapenet_r2n2``, BDM's units (``experiments/dataset/shapenet_r2n2.py``,
  ``normalize_per_shape=False``, as PointFlow): ``x_ref = (x_v1 − μ)/σ``, μ the mean point and σ the
  standard deviation (``torch.std``, n − 1) of every coordinate of every full PC15k cloud of the
  category in the evaluation split, after the v2 → v1 map. Then ``x_ref − mean = x_box / (s·σ)``:
  ``f = 1/(s·σ)``.
- ``reference`` on ``co3d``, PC²'s units: the sequence cloud's world units times PC²'s
  ``scale_factor = 1.0`` (``experiments/config/structured.py``): ``f = 1/s``. (Our Co3D loader drops the
  cloud's far outliers first, :mod:`cdm.data.co3d`; PC² keeps them.)
- ``reference`` on kinds without a reference code (procedural, meshes): ``f = 1``.
"""

from __future__ import annotations

from cdm.config import Config
from cdm.data.captured import CapturedDataset
from cdm.data.views import ObjectDataset

__all__ = ["score_factor"]


def score_factor(cfg: Config, dataset: ObjectDataset, index: int) -> float:
    """``f`` of the module docstring for held-out object ``index`` of ``dataset``."""
    if cfg.eval.normalise == "box" or not isinstance(dataset, CapturedDataset):
        return 1.0
    scale = dataset.surface(index).scale
    if cfg.data.kind == "shapenet_r2n2":
        return 1.0 / (scale * dataset.split_std(dataset.objects[index].category))
    return 1.0 / scale

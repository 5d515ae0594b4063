"""The embedded default data set: objects of the eight procedural shape categories
(:mod:`cdm.data.procedural_shapes`), generated on the fly.

:mod:`cdm.data.views` maps each object into its category's fixed frame (:data:`FRAMES`) and renders it.
Objects keep their own size and place in it: a small chair is small. Every object is fixed by its id
``procedural/<category>/<split>/<index>`` and ``data.seed``: the splits never share an object. Held out is
``val``, or ``tune`` with ``data.eval_split: tune`` (a recipe search's objects).
"""

from __future__ import annotations

import numpy as np

from cdm.config import Config
from cdm.data.procedural_shapes import CATEGORIES, GENERATOR_VERSION, make_shape
from cdm.data.views import ObjectDataset, Shape, interleave, select_categories
from cdm.normalise import Frame

__all__ = ["FRAMES", "ProceduralDataset"]

FRAMES: dict[str, Frame] = {
    name: Frame(centre, 1.0 / half)
    for name, (centre, half) in {
        "airplane": ((1.53, 0.15, 0.0), 1.83),
        "bottle": ((0.0, 1.24, 0.0), 1.27),
        "chair": ((0.0, 1.33, 0.19), 1.39),
        "lamp": ((0.33, 1.12, 0.0), 1.15),
        "mug": ((0.24, 0.65, 0.0), 0.88),
        "ring": ((0.0, 0.12, -0.15), 1.50),
        "sofa": ((0.0, 0.57, 0.09), 1.33),
        "table": ((0.0, 0.54, 0.0), 1.25),
    }.items()
}
"""Each category's frame (:mod:`cdm.normalise`), fixed for the data set: the union bounding box of 1,000 objects of
the category (seeds ``[7, i]``) in the world frame of :func:`make_shape`, its largest half-extent widened by 2 % and
rounded up. Every object fits ``[-1, 1]³`` in it; the median one reaches 0.6–0.8 (``tests/test_normalise.py``)."""


class ProceduralDataset(ObjectDataset):
    """``data.train_objects`` (or ``data.val_objects``) objects per category, categories interleaved.

    Object ``i`` of category ``c`` in ``split`` has id ``procedural/<c>/<split>/<i:05d>``; its shape,
    surface samples, colours and held-out view derive from that id and ``data.seed`` only.
    """

    kind = "procedural"

    @classmethod
    def categories(cls, cfg: Config) -> tuple[str, ...]:
        """The categories ``cfg.data.categories`` selects (all of :data:`CATEGORIES` when empty)."""
        return select_categories(cfg.data.categories, CATEGORIES, "the procedural data set")

    def _object_ids(self) -> list[tuple[str, str]]:
        count = self.cfg.data.train_objects if self.split == "train" else self.cfg.data.val_objects
        # The tuning split: a recipe search's own held-out objects, other ids than the tables' `val`.
        split = "tune" if self.split == "val" and self.cfg.data.eval_split == "tune" else self.split
        return interleave(
            [[(c, f"procedural/{c}/{split}/{i:05d}") for i in range(count)] for c in self.categories(self.cfg)]
        )

    def _shape(self, index: int, rng: np.random.Generator) -> Shape:
        return make_shape(self.objects[index].category, rng)

    def frame(self, category: str) -> Frame:
        return FRAMES[category]

    def _content_version(self) -> str:
        return f"generator {GENERATOR_VERSION}"

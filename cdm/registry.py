"""The lists of names a config accepts, one entry per name: its builder and the facts others ask of it.

Each list is a dict from the name a config holds (``data.kind``, ``priors.prior_2d``, ``diffusion.sampler``,
``priors.render_kind``) to one entry: its builder where one is chosen by name, and its facts. Whoever needs
a fact about a name (the protocol card's title of a data set, whether a 2D prior reads depth-map files)
reads it here instead of comparing strings. A builder is named by import path (``"module:attribute"``) and
imported on use, so this module stays light: the config and the sweep's plan stage read the facts without
importing torch. The ``Literal`` types of :mod:`cdm.config` keep the same names for static checkers and
pydantic's messages; ``tests/test_registry.py`` fails when a name is in one and not the other, or an
entry's builder is missing (a test, not a ``Literal`` built from these keys at run time, so that type
checkers still see each list).
"""

from __future__ import annotations

import importlib
from typing import Any, NamedTuple

__all__ = ["DATA_SETS", "PRIORS_2D", "RENDER_KINDS", "SAMPLERS", "DataSetEntry", "Prior2DEntry", "RenderEntry",
           "SamplerEntry", "load"]


def load(builder: str) -> Any:
    """The object ``"package.module:attribute"`` names, imported now."""
    module, _, attribute = builder.partition(":")
    return getattr(importlib.import_module(module), attribute)


class DataSetEntry(NamedTuple):
    """A data-set kind (``data.kind``)."""

    builder: str
    """Its :class:`cdm.data.views.ObjectDataset` subclass, built from the config and a split."""
    title: str
    """How the protocol card names it (``"Co3D v2"``)."""
    paper: bool
    """The paper reports on it (a captured data set, :data:`cdm.config.PaperDataSet`; the sweep side then
    holds its reference record in ``sweeps/plan/references.py``)."""


class Prior2DEntry(NamedTuple):
    """A 2D prior of the input image (``priors.prior_2d``, Eq. 7)."""

    builder: str
    """Its maker ``(image (3, S, S), mask (1, S, S), depth (1, S, S) | None) -> (channels, S, S)``."""
    channels: int
    """Channels it adds to the conditioning image features (Eq. 7)."""
    reads_depth: bool
    """It reads the sample's depth map: with ``priors.depth_source=maps`` that is a folder of estimated depth
    maps (``priors.depth_maps``), a file input the run needs."""


class SamplerEntry(NamedTuple):
    """A reverse-diffusion sampler (``diffusion.sampler``); :class:`cdm.diffusion.GaussianDiffusion` takes its
    steps by :attr:`ancestral`."""

    title: str
    """How a report names it."""
    ancestral: bool
    """It draws fresh noise each step from the posterior q(x_{t-1} | x_t, x̂₀) over all T steps or
    ``diffusion.ddpm_steps`` (DDPM); else a deterministic DDIM (η = 0) step over ``diffusion.sample_steps``
    spaced by ``diffusion.timestep_spacing``."""


class RenderEntry(NamedTuple):
    """What the 3D prior constraint renders (``priors.render_kind``, Eq. 6); :func:`cdm.render.splat_points`
    draws it by :attr:`depth`."""

    title: str
    """How a report names it."""
    depth: bool
    """It renders depth (needs the splat's Σwz channel and admits a front ``depth_layer``)."""


DATA_SETS: dict[str, DataSetEntry] = {
    "procedural": DataSetEntry("cdm.data.procedural:ProceduralDataset", "the procedural data set", paper=False),
    "meshes": DataSetEntry("cdm.data.meshes:MeshFolderDataset", "a mesh folder", paper=False),
    "shapenet_r2n2": DataSetEntry("cdm.data.shapenet:ShapeNetR2N2Dataset", "ShapeNet-R2N2 + PC15k", paper=True),
    "co3d": DataSetEntry("cdm.data.co3d:Co3DDataset", "Co3D v2", paper=True),
}
"""Data-set kinds by ``data.kind``."""

PRIORS_2D: dict[str, Prior2DEntry] = {
    "none": Prior2DEntry("cdm.data.priors2d:no_prior", channels=0, reads_depth=False),
    "contour": Prior2DEntry("cdm.data.priors2d:contour_prior", channels=1, reads_depth=False),
    "depth": Prior2DEntry("cdm.data.priors2d:depth_prior", channels=1, reads_depth=True),
}
"""2D priors by ``priors.prior_2d``."""

SAMPLERS: dict[str, SamplerEntry] = {
    "ddim": SamplerEntry("DDIM (η = 0)", ancestral=False),
    "ddpm": SamplerEntry("DDPM (ancestral)", ancestral=True),
}
"""Samplers by ``diffusion.sampler``."""

RENDER_KINDS: dict[str, RenderEntry] = {
    "depth": RenderEntry("depth maps", depth=True),
    "planar": RenderEntry("planar point images", depth=False),
}
"""3D-prior renderings by ``priors.render_kind``."""

"""cdm/registry.py: every name a config accepts has one complete entry, every entry's builder exists, and
docs/ARCHITECTURE.md's "Where a change goes" recipes add a data set and a 2D prior that a sweep can plan."""

import re
import shutil
import typing
from pathlib import Path

import pytest
import torch

from cdm.config import DataKind, PaperDataSet, Prior2D, RenderKind, Sampler, load_config
from cdm.data import DATASETS
from cdm.data.views import ObjectDataset
from cdm.registry import DATA_SETS, PRIORS_2D, RENDER_KINDS, SAMPLERS, load
from sweeps.plan.protocol import CardContext, protocol_card
from sweeps.plan.references import RECORDS
from tests.hostile_files import ROOT, run_command


@pytest.mark.parametrize(
    ("allowed", "registry"),
    [(DataKind, DATA_SETS), (Prior2D, PRIORS_2D), (Sampler, SAMPLERS), (RenderKind, RENDER_KINDS)],
    ids=["data.kind", "priors.prior_2d", "diffusion.sampler", "priors.render_kind"],
)
def test_every_name_the_config_accepts_has_an_entry_and_no_entry_lacks_a_name(allowed, registry):
    assert list(registry) == list(typing.get_args(allowed))


def test_the_paper_data_sets_are_the_entries_marked_paper_and_each_has_a_reference_record():
    paper = [kind for kind, entry in DATA_SETS.items() if entry.paper]
    assert paper == list(typing.get_args(PaperDataSet)) == ["shapenet_r2n2", "co3d"]
    assert list(RECORDS) == paper


def test_each_data_set_entry_builds_its_own_kind_and_has_a_title():
    for kind, entry in DATA_SETS.items():
        cls = load(entry.builder)
        assert issubclass(cls, ObjectDataset) and cls.kind == kind and DATASETS[kind] is cls
        assert entry.title.strip()


def test_each_2d_prior_maker_gives_the_channels_its_entry_states():
    image, mask = torch.rand(3, 16, 16), torch.zeros(1, 16, 16)
    mask[:, 4:12, 4:12] = 1.0
    depth = mask * torch.linspace(1.0, 2.0, 16)
    for kind, entry in PRIORS_2D.items():
        channels = load(entry.builder)(image, mask, depth)
        assert channels.shape == (entry.channels, 16, 16), kind
    assert [kind for kind, entry in PRIORS_2D.items() if entry.reads_depth] == ["depth"]


def test_the_sampler_and_render_entries_state_their_facts():
    assert {k: e.ancestral for k, e in SAMPLERS.items()} == {"ddim": False, "ddpm": True}
    assert {k: e.depth for k, e in RENDER_KINDS.items()} == {"depth": True, "planar": False}
    assert all(e.title.strip() for e in (*SAMPLERS.values(), *RENDER_KINDS.values()))


@pytest.mark.parametrize("kind", typing.get_args(DataKind))
def test_the_protocol_card_names_every_data_set_kind(kind):
    lines = protocol_card(load_config(None, {"data.kind": kind}), CardContext(datasets=("co3d",))).lines()
    expected = [] if kind == "co3d" else [f"deviation: data set: {DATA_SETS[kind].title} stands in for Co3D v2"]
    assert [line for line in lines if "data set:" in line] == expected


def _edit(path: Path, pattern: str, replacement: str) -> None:
    """Replace the one match of ``pattern`` in ``path``, failing when the recipe's anchor moved."""
    text, count = re.subn(pattern, replacement, path.read_text(), count=1)
    assert count == 1, f"{pattern!r} not found in {path}"
    path.write_text(text)


def _append(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


@pytest.mark.slow
def test_recipes_add_a_data_set_and_a_2d_prior(tmp_path):
    """docs/ARCHITECTURE.md's recipes followed in a copy of the repository, file by file as they name them,
    then a smoke dry run of a spec on the new kind and prior."""
    copy = tmp_path / "repo"
    for folder in ("cdm", "sweeps", "configs"):
        shutil.copytree(ROOT / folder, copy / folder, ignore=shutil.ignore_patterns("__pycache__"))
    # A new data set: one module in cdm/data/, its entry in DATA_SETS, its name in DataKind.
    (copy / "cdm/data/dummy.py").write_text(
        '"""A dummy data set: the procedural objects under another kind."""\n\n'
        "from cdm.data.procedural import ProceduralDataset\n\n\n"
        "class DummyDataset(ProceduralDataset):\n"
        '    kind = "dummy"\n'
    )
    _append(copy / "cdm/registry.py",
            '\nDATA_SETS["dummy"] = DataSetEntry("cdm.data.dummy:DummyDataset", "the dummy data set", paper=False)\n')
    _edit(copy / "cdm/config.py", r"DataKind = Literal\[", 'DataKind = Literal["dummy", ')
    # A new 2D prior: its maker in cdm/data/priors2d.py, its entry in PRIORS_2D, its name in Prior2D.
    _append(copy / "cdm/data/priors2d.py",
            "\n\ndef blank_prior(image: Tensor, mask: Tensor, depth: Tensor | None) -> Tensor:\n"
            "    return image.new_zeros(2, *image.shape[1:])\n")
    _append(copy / "cdm/registry.py",
            '\nPRIORS_2D["blank"] = Prior2DEntry("cdm.data.priors2d:blank_prior", channels=2, reads_depth=False)\n')
    _edit(copy / "cdm/config.py", r"Prior2D = Literal\[", 'Prior2D = Literal["blank", ')

    out = run_command(["sweeps/run.py", "sweeps/point_size.yaml", "--smoke", "--dry-run", "--no-estimate",
                       "--set", "data.kind=dummy", "--set", "priors.prior_2d=blank"], copy, timeout=300,
                      env={"PYTHONPATH": str(copy)})
    assert out.code == 0, out.stderr
    assert "data set: the dummy data set stands in for" in out.stdout
    assert "priors.prior_2d: blank, not depth" in out.stdout

"""Loading and validation of cdm.config."""

import ast
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from cdm.config import Config, ConfigError, apply_overrides, config_field_paths, load_config, parse_override

ROOT = Path(__file__).resolve().parent.parent


def test_defaults_are_the_papers():
    c = Config()
    assert c.priors.point_size == 0.04 and c.priors.num_views == 10 and c.priors.target == "x0_hat"
    assert c.model.raster_radius == 0.0075 and c.diffusion.num_steps == 1000
    assert (c.diffusion.beta_start, c.diffusion.beta_end) == (1e-5, 8e-3)
    assert c.train.lr == 1e-3 and c.train.batch_size == 8 and c.data.image_size == 224


def test_yaml_file_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("priors:\n  lambda_3d: 0.5\nmodel:\n  widths: [16, 32]\n  voxel_resolutions: [8, 4]\n")
    c = load_config(
        path, overrides=dict([parse_override("priors.num_views=4"), parse_override("data.categories=[chair, mug]")])
    )
    assert c.priors.lambda_3d == 0.5 and c.priors.num_views == 4
    assert c.model.widths == (16, 32) and c.data.categories == ("chair", "mug")
    assert load_config(c.to_dict()) == c
    assert c.flat()["priors.num_views"] == 4


@pytest.mark.parametrize(
    "tree,field",
    [
        ({"priors": {"lamda_3d": 1.0}}, "priors.lamda_3d"),
        ({"priors": {"lambda_3d": -1.0}}, "priors.lambda_3d"),
        ({"priors": {"num_views": 0}}, "priors.num_views"),
        ({"priors": {"render_kind": "mesh"}}, "priors.render_kind"),
        ({"model": {"widths": [16], "voxel_resolutions": [8, 4]}}, "model.widths"),
        ({"train": {"steps": "many"}}, "train.steps"),
        ({"optimizer": {}}, "optimizer"),
    ],
)
def test_bad_values_name_the_field(tree, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        load_config(tree)


def test_prior_off_allows_zero_views():
    assert load_config({"priors": {"prior_3d": False, "num_views": 0}}).priors.num_views == 0


def test_unknown_override_and_bad_file(tmp_path):
    with pytest.raises(ConfigError, match="priors.size"):
        apply_overrides({}, {"priors.size": 1})
    with pytest.raises(ConfigError, match="key=value"):
        parse_override("priors.point_size")
    bad = tmp_path / "bad.yaml"
    bad.write_text("priors: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="missing.yaml does not exist"):
        load_config(tmp_path / "missing.yaml")


def test_field_paths_cover_every_group():
    paths = config_field_paths()
    assert "priors.point_size" in paths and "model.global_feature" in paths and "eval.f1_threshold" in paths
    assert all(p.split(".")[0] in Config.model_fields for p in paths)


def test_replace_sets_dotted_fields_through_the_same_validation():
    cfg = load_config(None, {"priors.lambda_3d": 0.5})
    out = cfg.replace(**{"train.out_dir": "/tmp/x", "model.voxel_backend": "sparse", "sampling.blend.seed": 3})
    assert (out.train.out_dir, out.model.voxel_backend, out.sampling.blend.seed) == ("/tmp/x", "sparse", 3)
    assert out.priors.lambda_3d == 0.5 and cfg.train.out_dir == "runs/cdm"  # the rest kept, the original untouched
    assert out.replace() == out
    with pytest.raises(ConfigError, match=r"^priors\.lambda_3d: Input should be greater than or equal to 0"):
        cfg.replace(**{"priors.lambda_3d": -1.0})
    with pytest.raises(ConfigError, match=r"^train\.stpes: unknown config field"):
        cfg.replace(**{"train.stpes": 3})
    with pytest.raises(ConfigError, match="sampling.blend.prior_checkpoint is required"):
        cfg.replace(**{"sampling.blend.enabled": True})


@pytest.mark.parametrize(("text", "said"), [
    ("data.categories=" + "[" * 2000 + "]" * 2000, "data.categories: the value is nested 2000 deep; at most 64"),
    ("data.num_points=" + "9" * 5001, "data.num_points: the value is not valid YAML: an integer of 5001 digits"),
])
def test_a_set_value_nested_deep_or_of_5001_digits_is_one_config_error(text, said):
    with pytest.raises(ConfigError, match=said) as refused:
        parse_override(text)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize(
    ("kind", "said"),
    [
        ("fifo", "is a FIFO; expected a regular file"),
        ("deep", "nested 100000 deep; at most 64"),
        ("latin1", "not UTF-8 text"),
    ],
)
def test_a_config_file_that_is_a_fifo_nested_deep_or_not_utf8_is_refused(tmp_path, kind, said):
    import os

    path = tmp_path / "config.yaml"
    if kind == "fifo":
        os.mkfifo(path)  # no writer: reading it would wait forever
    elif kind == "deep":
        path.write_text("[" * 100_000 + "]" * 100_000)
    else:
        path.write_bytes(b"train: {steps: \xe9}\n")
    with pytest.raises(ConfigError, match=said):
        load_config(path)


def _field_literals(model: type[BaseModel] = Config) -> set[frozenset]:
    """The allowed-value lists of every config field, each as a set of its values."""
    found = set()
    for info in model.model_fields.values():
        if isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel):
            found |= _field_literals(info.annotation)
        elif typing.get_origin(info.annotation) is typing.Literal:
            found.add(frozenset(typing.get_args(info.annotation)))
    return found


def _literals_written(source: str) -> list[frozenset]:
    """The ``Literal[...]`` lists written out in a module's source."""
    lists = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Subscript) and getattr(node.value, "id", None) == "Literal":
            items = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            if all(isinstance(i, ast.Constant) for i in items):
                lists.append(frozenset(i.value for i in items))
    return lists


def test_each_allowed_value_list_of_the_config_is_written_once_and_imported_elsewhere():
    """cdm/config.py's Literals (DataKind, Prediction, RenderKind, Prior2D, ...) are the lists' one home."""
    lists = _field_literals()
    assert frozenset({"depth", "planar"}) in lists and frozenset({"eps", "x0", "v"}) in lists
    again = [
        (str(path.relative_to(ROOT)), sorted(values))
        for folder in ("cdm", "sweeps")
        for path in sorted((ROOT / folder).rglob("*.py"))
        if path != ROOT / "cdm" / "config.py"
        for values in _literals_written(path.read_text())
        if values in lists
    ]
    assert again == []
    planted = 'def splat(kind: Literal["depth", "planar"]) -> None: ...'
    assert frozenset({"depth", "planar"}) in _literals_written(planted)


def test_the_tuning_split_is_the_procedural_data_sets_own_and_shares_no_object_with_val():
    from cdm.data import build_dataset

    cfg = load_config(None, {"data.categories": ["chair", "ring"], "data.val_objects": 3})
    tune = build_dataset(cfg.replace(**{"data.eval_split": "tune"}), "val")
    val = build_dataset(cfg, "val")
    assert [o.object_id for o in tune.objects][:2] == ["procedural/chair/tune/00000", "procedural/ring/tune/00000"]
    assert len(tune.objects) == len(val.objects) == 6
    assert not {o.object_id for o in tune.objects} & {o.object_id for o in val.objects}
    with pytest.raises(ConfigError, match="data.eval_split: tune is the procedural data set's tuning split"):
        load_config(None, {"data.kind": "meshes", "data.root": "/nowhere", "data.eval_split": "tune"})

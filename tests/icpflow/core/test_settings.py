"""One way to check a config (icpflow.core.settings): every entry point's config is a structured config whose types and
keys Hydra checks while composing, and whose rules check_config checks before any work."""

import copy
import dataclasses
import inspect
import typing

import lightning as L
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from fastflow3d.training.options import ExportOptions, TrainerOptions, TrainOptions
from icpflow.core.errors_and_signals import error_line
from icpflow.core.settings import RULES, OptionError, accepts, check_config, signature_schema
from icpflow.evaluation.options import EvalOptions
from icpflow.labelling.options import DatasetOptions, LabelOptions

from helpers.data import REPO

CONF = REPO / "conf"
SCHEMAS = {"label": LabelOptions, "eval": EvalOptions, "train": TrainOptions, "export": ExportOptions}
#: a value of each rule's type that breaks it (rules a value of the field's own type cannot break are absent)
BREAKS = {
    "positive": -1.0,
    "non_negative": -0.5,
    "fraction": 1.5,
    "count": 0,
    "count_or_zero": -1,
    "odd_count": 2,
    "count_or_none": 0,
    "pixel_size": [0, 720],
}


def _compose(name: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(name, [*overrides, "checkpoint=x.ckpt"] if name == "export" else list(overrides))


def _ruled_fields(cfg, prefix=""):
    """(full key, field) for every field with a rule or choices in ``cfg`` and its typed sub-blocks."""
    kind = OmegaConf.get_type(cfg)
    if dataclasses.is_dataclass(kind):
        for f in dataclasses.fields(kind):
            if f.metadata.get("rule") or f.metadata.get("choices"):
                yield f"{prefix}{f.name}", f
    for key in cfg:
        if not OmegaConf.is_missing(cfg, key) and OmegaConf.is_dict(cfg._get_node(key)) and cfg[key] is not None:
            yield from _ruled_fields(cfg[key], f"{prefix}{key}.")


@pytest.mark.parametrize("name", SCHEMAS)
def test_each_entry_config_is_its_schema_and_its_defaults_obey_the_rules(name):
    cfg = _compose(name)
    assert OmegaConf.get_type(cfg) is SCHEMAS[name]
    check_config(cfg)
    if name in ("label", "eval"):
        assert OmegaConf.get_type(cfg.dataset) is DatasetOptions
        # every teacher block is typed, in icpflow.* and in the dataset's teacher block
        for block in ("icpflow", "dataset.teacher"):
            node = OmegaConf.select(cfg, block)
            for key in ("clustering", "ground", "ego_motion", "icp", "deskew", "association"):
                assert dataclasses.is_dataclass(OmegaConf.get_type(node[key])), f"{block}.{key}"


@pytest.mark.parametrize("name", SCHEMAS)
def test_a_value_breaking_any_rule_is_one_line_naming_the_option(name):
    """Each field with a rule or choices, given a value of its type that breaks it: OptionError naming it."""
    checked = 0
    composed = _compose(name)
    for key, f in _ruled_fields(composed):
        rule, choices = f.metadata.get("rule"), f.metadata.get("choices")
        value = "bogus" if choices else BREAKS.get(rule)
        if value is None:
            continue
        cfg = copy.deepcopy(composed)
        OmegaConf.update(cfg, key, value, merge=False)
        with pytest.raises(OptionError) as refused:
            check_config(cfg)
        line = str(refused.value)
        assert line.startswith(f"{key} must be ") and repr(value) in line and "\n" not in line, line
        checked += 1
    assert checked >= (0 if name == "export" else 5)


@pytest.mark.parametrize(
    "name, override, words",
    [
        ("label", "limit=abc", "limit=abc: expected an integer, got 'abc'"),
        ("label", "tracker=maybe", "tracker=maybe: expected true or false, got 'maybe' (the default is False)"),
        ("label", "limt=3", "limt=3: limt is not an option (did you mean limit?)"),
        ("label", "ray.adress=auto", "ray.adress=auto: ray.adress is not an option (did you mean ray.address?)"),
        ("label", "icpflow.clustering.min_cluster_size=many", "expected an integer, got 'many'"),
        ("eval", "crop=wide", "crop=wide: expected a number, got 'wide' (the default is 32.0)"),
        ("eval", "dataset.teacher.icp.max_itr=3", "dataset.teacher.icp.max_itr is not an option (did you mean"),
        ("train", "data.batch_size=abc", "data.batch_size=abc: expected an integer, got 'abc' (the default is 4)"),
        ("train", "trainer.max_steps=abc", "trainer.max_steps=abc: expected an integer, got 'abc'"),
        ("train", "trainer.max_stepz=3", "trainer.max_stepz is not an option (did you mean trainer.max_steps?)"),
        ("train", "trainer.limit_val_batches=some", "trainer.limit_val_batches=some: expected a number, got 'some'"),
        ("train", "export.formats=onnx", "export.formats=onnx: expected a list, e.g. [a,b], got 'onnx'"),
        ("train", "loss=speed", "loss=speed: loss is a block of settings, give one of its fields"),
        ("export", "format=3", None),  # an int is a text's value: accepted
        # the _target_ groups (issue 45.5): their own keys, with the nearest one
        ("train", "model.correlation_levls=[1]", "model.correlation_levls is not an option (did you mean model.corr"),
        ("train", "optim.lrr=0.1", "optim.lrr is not an option (did you mean optim.lr?)"),
        ("train", "scheduler.warmup_fractio=0.1", "scheduler.warmup_fractio is not an option (did you mean"),
    ],
)
def test_a_wrong_type_or_an_unknown_key_is_refused_while_composing(name, override, words):
    if words is None:
        _compose(name, override)
        return
    with pytest.raises(ConfigCompositionException) as refused:
        _compose(name, override)
    line = error_line(refused.value)
    assert words in line and "\n" not in line, line
    assert line.endswith("; see `--help` and `--cfg job` for the options")


@pytest.mark.parametrize("name", ["label", "train"])
def test_a_key_added_with_plus_is_refused_before_any_work(name):
    cfg = _compose(name, "+limt=3", "+data.batch_sise=2" if name == "train" else "+ray.port=1")
    with pytest.raises(OptionError, match="is not an option"):
        check_config(cfg)


@pytest.mark.parametrize(
    "override, words",
    [
        ("+model.correlation_levls=[1]", "model.correlation_levls is not an option (did you mean model.correlation_"),
        ("+optim.lrr=0.1", "optim.lrr is not an option (did you mean optim.lr?) of torch.optim.Adam"),
        ("model.correlation_levels=abc", "model.correlation_levels=abc: expected a list, e.g. [a,b], got 'abc'"),
        ("model.correlation_levels=7", "model.correlation_levels=7: expected a list, e.g. [a,b], got 7"),
        ("model.cell=abc", "model.cell=abc: expected a number, got 'abc'"),
        ("model.cell=true", "model.cell=True: expected a number, got True"),
        ("model.decoder=3", "model.decoder=3: expected a text, got 3"),
        ("optim.lr=abc", "optim.lr=abc: expected a number, got 'abc'"),
    ],
)
def test_a_target_groups_arguments_are_checked_against_its_signature(override, words):
    """model, optim, scheduler, ... are _target_ nodes: an argument added with + or of the wrong kind was an
    "unexpected TypeError" when the class was built (issue 45.5); now one line naming it, before any work."""
    cfg = _compose("train", override)
    with pytest.raises(OptionError) as refused:
        check_config(cfg)
    assert words in str(refused.value) and "\n" not in str(refused.value), refused.value


def test_the_trainer_schema_is_lightnings_signature():
    """Every Trainer keyword argument (less those the code passes) is an option, with Lightning's default; an
    int-or-float argument keeps an int an int (limit_val_batches=4: four batches, not 4.0 of them)."""
    names = {f.name for f in dataclasses.fields(TrainerOptions)}
    expected = set(inspect.signature(L.Trainer).parameters)
    assert names == expected - {"logger", "callbacks", "plugins", "default_root_dir"}
    cfg = _compose("train", "trainer.limit_val_batches=4", "trainer.limit_train_batches=0.5")
    assert type(cfg.trainer.limit_val_batches) is int and cfg.trainer.limit_train_batches == 0.5
    defaults = OmegaConf.structured(TrainerOptions)
    assert defaults.inference_mode is True and defaults.num_nodes == 1
    assert all(rule in RULES for rule in BREAKS)


def test_signature_schema_types():
    def target(a: int = 1, b: float | None = None, c: typing.Literal["x", 3] = "x", d: list[int] = None):  # noqa: RUF013
        return a

    schema = signature_schema(target, "Target")
    hints = typing.get_type_hints(schema)
    assert hints["a"] is int and hints["b"] == float | None and hints["c"] == str | int and hints["d"] is typing.Any
    with pytest.raises(ValueError, match="has no default"):
        signature_schema(lambda x: x, "Lambda")


@pytest.mark.parametrize(
    "rule, good, bad",
    [
        ("count", 1, 0),
        ("positive", 0.1, 0.0),
        ("fraction", 1.0, 1.01),
        ("odd_count", 3, 4),
        ("pixel_size", [640, 480], [640]),
        ("integer", -3, 2.0),
        ("number", 1, float("nan")),
    ],
)
def test_rules(rule, good, bad):
    assert accepts(rule, good) and not accepts(rule, bad) and not accepts(rule, True if rule != "flag" else 1)


def test_a_path_given_as_tilde_is_the_home_folder_not_a_folder_named_tilde(monkeypatch, tmp_path):
    """out_dir='~/x' (quoted: no shell expands it) made a literal ./~/x folder and printed a path that read as the
    home (issue 45.5): the folders Hydra makes and those our code makes are under the home."""
    monkeypatch.setenv("HOME", str(tmp_path))
    cfg = _compose("train", "out_dir='~/x'", "data.train='~/labels'")
    assert cfg.hydra_dir == f"{tmp_path}/x/hydra"  # Hydra's run folder, made before any code of ours
    check_config(cfg)
    assert (cfg.out_dir, cfg.checkpoint_dir, cfg.data.train) == (
        f"{tmp_path}/x",
        f"{tmp_path}/x/checkpoints",
        f"{tmp_path}/labels",
    )

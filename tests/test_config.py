from pathlib import Path

import pytest

import torchsfm
from torchsfm.config import Config, config_from_dict, config_to_dict, load_config, with_overrides
from torchsfm.errors import ConfigError

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


def test_default_yaml_holds_every_default():
    assert load_config(DEFAULT_YAML) == Config()


def test_default_yaml_lists_every_key():
    import yaml

    assert yaml.safe_load(DEFAULT_YAML.read_text()) == config_to_dict(Config())


def test_unknown_key_is_named():
    with pytest.raises(ConfigError, match="fundamental.ransac.confidense"):
        config_from_dict({"fundamental": {"ransac": {"confidense": 0.9}}})


def test_unknown_section_is_named():
    with pytest.raises(ConfigError, match="'featurez'"):
        config_from_dict({"featurez": {}})


def test_wrong_type_is_named():
    with pytest.raises(ConfigError, match="fundamental.ransac.max_trials"):
        config_from_dict({"fundamental": {"ransac": {"max_trials": "many"}}})
    with pytest.raises(ConfigError, match="fundamental.refine"):
        config_from_dict({"fundamental": {"refine": 1}})
    with pytest.raises(ConfigError, match="pairs.mode=3 must be one of auto, sequential"):
        config_from_dict({"pairs": {"mode": 3}})


def test_out_of_range_value_is_named():
    with pytest.raises(ConfigError, match=r"fundamental.ransac.confidence=1.5"):
        config_from_dict({"fundamental": {"ransac": {"confidence": 1.5}}})
    with pytest.raises(ConfigError, match="triangulation.method"):
        config_from_dict({"triangulation": {"method": "magic"}})
    with pytest.raises(ConfigError, match=r"reconstruction.refined_intrinsics='f,cx\|f,k2' is invalid: .*alternatives separated by \|"):
        config_from_dict({"reconstruction": {"refined_intrinsics": "f,cx|f,k2"}})
    with pytest.raises(ConfigError, match=r"matching.relative_distance_threshold=2.5 .*never exceeds 2"):
        config_from_dict({"matching": {"relative_distance_threshold": 2.5}})


def test_yaml_floats_without_a_dot_are_accepted(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("lm:\n  gradient_tolerance: 1e-8\n")
    assert load_config(path).lm.gradient_tolerance == 1e-8


def test_overrides():
    config = with_overrides(Config(), ["fundamental.ransac.inlier_threshold=2.5", "triangulation.method=midpoint"])
    assert config.fundamental.ransac.inlier_threshold == 2.5
    assert config.triangulation.method == "midpoint"
    with pytest.raises(ConfigError, match="fundamental.ransac.nope"):
        with_overrides(Config(), ["fundamental.ransac.nope=1"])
    with pytest.raises(ConfigError, match="section.key=value"):
        with_overrides(Config(), ["no_equals_sign"])
    with pytest.raises(ConfigError, match="config fundamental.ransac must be a mapping, got int"):
        with_overrides(Config(), ["fundamental.ransac=1"])


def test_unreadable_and_invalid_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("fundamental: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)


def test_public_exports():
    assert torchsfm.load_config is load_config


def test_registries_offer_exactly_the_config_choices():
    from typing import get_args

    from torchsfm.config import MotionModel, PoseMethod, Sampler, Scoring, TriangulationMethod
    from torchsfm.geometry.essential import POSE_CANDIDATES
    from torchsfm.geometry.triangulation import TRIANGULATION_METHODS
    from torchsfm.moving.hypotheses import MODELS
    from torchsfm.robust.ransac import SCORINGS
    from torchsfm.robust.samplers import SAMPLERS

    for registry, choices in ((SAMPLERS, Sampler), (SCORINGS, Scoring), (TRIANGULATION_METHODS, TriangulationMethod),
                              (POSE_CANDIDATES, PoseMethod), (MODELS, MotionModel)):
        assert set(registry) == set(get_args(choices))


@pytest.mark.parametrize("key, value", [("triangulation.method", "linear"), ("matching.strength", "zncc"),
                                        ("pairs.mode", "random"), ("moving_objects.track_method", "votes")])
def test_an_unknown_choice_is_named_with_its_choices(key, value):
    with pytest.raises(ConfigError, match=f"{key}='{value}' is invalid: one of "):
        with_overrides(Config(), [f"{key}={value}"])

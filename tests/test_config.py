"""One `from_dict` policy (core/config.py): an unknown or mistyped key is a ConfigError that
names the key and where it came from, for every config dataclass alike."""

from __future__ import annotations

import json

import pytest

from topseg.core.camera import PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.config import from_dict
from topseg.core.crf.energy import CRFConfig
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.train import TrainConfig
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.synthesis import SynthesisConfig

CONFIGS = [CRFConfig, SynthesisConfig, DensityConfig, TrainConfig, FeatureConfig, TopViewMount]


def test_config_error_is_the_operators_error_and_a_value_error():
    assert issubclass(ConfigError, TopsegError) and issubclass(ConfigError, ValueError)


@pytest.mark.parametrize("cls", [*CONFIGS, Intrinsics])
def test_every_config_round_trips(cls):
    value = (
        PAPER_MOUNT.intrinsics
        if cls is Intrinsics
        else PAPER_MOUNT
        if cls is TopViewMount
        else cls()
    )
    data = json.loads(json.dumps(value.to_dict()))
    assert cls.from_dict(data, source="x.json").to_dict() == value.to_dict()


@pytest.mark.parametrize("cls", CONFIGS)
def test_an_unknown_key_names_it_and_the_source(cls):
    data = json.loads(json.dumps((PAPER_MOUNT if cls is TopViewMount else cls()).to_dict()))
    data["colour"] = 1
    with pytest.raises(ConfigError, match=r"^cell1\.toml \[x\]: unknown key 'colour'"):
        cls.from_dict(data, source="cell1.toml [x]")


@pytest.mark.parametrize(
    ("cls", "key", "value", "expected"),
    [
        (CRFConfig, "smoothness", "strong", "a number"),
        (CRFConfig, "ring", 1.5, "an integer"),
        (CRFConfig, "mode", "fast", "one of 'none', 'exact', 'realtime'"),
        (TrainConfig, "max_depth", True, "an integer"),
        (TrainConfig, "split", 3, "a string"),
        (FeatureConfig, "n_features", "300", "an integer"),
        (SynthesisConfig, "room", 7, "a string or null"),
        (SynthesisConfig, "density", [1], "a table"),
        (DensityConfig, "human_height_m", [1.6], "a list of 2"),
    ],
)
def test_a_mistyped_key_names_it_and_the_source(cls, key, value, expected):
    with pytest.raises(ConfigError) as err:
        cls.from_dict({key: value}, source="model.npz header")
    message = str(err.value)
    assert message.startswith("model.npz header: ") and f"{key} must be {expected}" in message


def test_a_nested_key_names_its_path():
    with pytest.raises(ConfigError, match=r"^m\.npz recipe\.features: unknown key 'n_feature' "):
        TrainConfig.from_dict({"features": {"n_feature": 3}}, source="m.npz recipe")
    with pytest.raises(ConfigError, match=r"^attrs\.density: theta_max_ho must be a number"):
        SynthesisConfig.from_dict({"density": {"theta_max_ho": "x"}}, source="attrs")
    with pytest.raises(ConfigError, match=r"^attrs\.camera\.intrinsics: missing key 'fy'"):
        SynthesisConfig.from_dict(
            {"camera": {"height_mm": 3000, "intrinsics": {"width": 64, "height": 48, "fx": 1}}},
            source="attrs",
        )


def test_a_rejected_value_is_a_config_error_with_the_source():
    # ValueError (TrainConfig) and TopsegError (CRFConfig) from the classes alike
    with pytest.raises(ConfigError, match=r"^t\.toml: max_depth must be in \[0, 30\]"):
        TrainConfig.from_dict({"max_depth": 40}, source="t.toml")
    with pytest.raises(ConfigError, match=r"^t\.toml: crf ring must be >= 0"):
        CRFConfig.from_dict({"ring": -1}, source="t.toml")
    with pytest.raises(ConfigError, match="expected a table"):
        CRFConfig.from_dict(["realtime"])


def test_missing_keys_take_defaults_and_numbers_are_normalised():
    """A file that lacks a newer field still loads; ints become floats where declared."""
    assert TrainConfig.from_dict({"n_trees": 2}) == TrainConfig(n_trees=2)
    features = FeatureConfig().to_dict()
    del features["absolute_fraction"]  # older model headers lack it
    assert FeatureConfig.from_dict(features) == FeatureConfig()
    crf = CRFConfig.from_dict({"smoothness": 2})
    assert crf.smoothness == 2.0 and isinstance(crf.smoothness, float)
    mount = TopViewMount.from_dict(
        {"intrinsics": PAPER_MOUNT.intrinsics.to_dict(), "height_mm": 3000}
    )
    assert isinstance(mount.height_mm, float)


def test_the_helper_reads_any_dataclass():
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Small:
        size: tuple[int, int] = (1, 2)
        name: str | None = None

    assert from_dict(Small, {"size": [3, 4]}) == Small((3, 4))
    with pytest.raises(ConfigError, match=r"^Small: size must be a list of 2"):
        from_dict(Small, {"size": [3, "4"]})
    with pytest.raises(ConfigError, match=r"^Small: missing key 'name'"):
        from_dict(Small, {}, required=("name",))

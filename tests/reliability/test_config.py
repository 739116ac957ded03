"""Config validation at load: every numeric setting has a range, and a value outside it names the key."""

import dataclasses
import math

import pytest

from runtime.dense import DenseConfig
from runtime.slam import SlamConfig


def _numeric(obj, path):
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _numeric(v, f"{path}.{f.name}")
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            yield type(obj), f.name, v, f"{path}.{f.name}"


@pytest.mark.parametrize("cfg", [SlamConfig(), DenseConfig()], ids=["runtime", "dense_settings"])
def test_every_numeric_default_lies_in_its_range(cfg):
    from runtime.config import value_range

    n = 0
    for cls, name, v, key in _numeric(cfg, "x"):
        lo, hi = value_range(cls, name)
        assert lo <= v <= hi, f"{key}={v} outside [{lo}, {hi}]"
        n += 1
    assert n >= 17


@pytest.mark.parametrize(
    "d, message",
    [
        ({"backend": {"window_size": 0}}, "runtime.backend.window_size=0 is out of range: must be >= 2"),
        ({"features": {"max_features": 0}}, "runtime.features.max_features=0 is out of range: must be >= 1"),
        ({"backend": {"pixel_sigma": 0.0}}, "runtime.backend.pixel_sigma=0.0 is out of range: must be > 0"),
        ({"tracker": {"ransac_confidence": 1.5}}, "runtime.tracker.ransac_confidence=1.5 is out of range"),
        ({"keyframes": {"max_interval_s": -1.0}}, "runtime.keyframes.max_interval_s=-1.0 is out of range"),
        ({"imu": {"gravity": math.nan}}, "runtime.imu.gravity must be finite"),
    ],
)
def test_a_value_out_of_range_is_refused_naming_the_key(d, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
        SlamConfig.from_dict(d)


def test_dense_settings_are_checked_too():
    with pytest.raises(ValueError, match=r"dense_settings\.factors\.chunk_size=0 is out of range"):
        DenseConfig.from_dict({"factors": {"chunk_size": 0}})

"""Fixtures for runtime.io tests."""

from __future__ import annotations

import pytest

from tests.io.fake_euroc import FakeEuroc, make_euroc


@pytest.fixture
def euroc(tmp_path) -> FakeEuroc:
    """Default tiny sequence (cam0 yaml with ``%YAML:1.0``, imu0 yaml without, depth0, cam1/leica0)."""
    return make_euroc(tmp_path / "MH_01_tiny")


@pytest.fixture
def euroc_factory(tmp_path):
    """``make(name, **kw) -> FakeEuroc`` for variants (see :func:`make_euroc`)."""

    def make(name: str = "seq", **kw) -> FakeEuroc:
        return make_euroc(tmp_path / name, **kw)

    return make

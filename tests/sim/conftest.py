"""Sequences shared by the sim tests (rendered once per session, small and seeded)."""

from __future__ import annotations

import pytest

from sim.euroc import write_euroc_sequence

#: IMU index range of a moving second of EXACT_SEQ (3.4 s .. 4.4 s: after the 2.5 s rest, during the ramp-up).
MOVING = (680, 880)


@pytest.fixture(scope="session")
def exact_seq(tmp_path_factory):
    """Full-resolution (752x480) textured sequence, 4.5 s, exact IMU (imu_noise=False), seed 1."""
    out = tmp_path_factory.mktemp("euroc_exact")
    return write_euroc_sequence(out, "textured", duration=4.5, seed=1, imu_noise=False, progress=False, realism=False)


@pytest.fixture(scope="session")
def noisy_small_seq(tmp_path_factory):
    """Quarter-resolution textured sequence, 3 s, noisy IMU, seed 2 (layout and bias checks)."""
    out = tmp_path_factory.mktemp("euroc_noisy")
    return write_euroc_sequence(
        out, "textured", duration=3.0, seed=2, imu_noise=True, progress=False, scale=0.25, realism=False
    )

"""Visual-inertial initialisation: at rest (:mod:`runtime.init.static`) or in motion (:mod:`runtime.init.dynamic`)."""

from runtime.init.dynamic import DynamicInitConfig, DynamicResult, InitFailed, initialize_in_motion
from runtime.init.static import (
    InitConfig,
    InitResult,
    RestStats,
    StaticInitializer,
    gravity_aligned_rotation,
    imu_rest_stats,
)

__all__ = [
    "DynamicInitConfig",
    "DynamicResult",
    "InitConfig",
    "InitFailed",
    "InitResult",
    "RestStats",
    "StaticInitializer",
    "gravity_aligned_rotation",
    "imu_rest_stats",
    "initialize_in_motion",
]

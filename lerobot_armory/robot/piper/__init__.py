"""AgileX PiPER adapter (``--robot.type=piper``); see ``docs/piper.md``.

``PiperConfig`` registers the ``piper`` robot type without importing piper_sdk; LeRobot's
``make_robot_from_config`` then finds ``Piper`` here (config class name minus ``Config``).
"""

from .config_piper import GRIPPER_RANGE_MM, JOINT_LIMITS_DEG, JOINT_NAMES, MOTOR_NAMES, PiperConfig
from .piper import (
    Piper,
    PiperConnectionError,
    PiperEnableTimeoutError,
    PiperError,
    PiperNoFeedbackError,
    clamp_targets,
)

__all__ = [
    "GRIPPER_RANGE_MM",
    "JOINT_LIMITS_DEG",
    "JOINT_NAMES",
    "MOTOR_NAMES",
    "Piper",
    "PiperConfig",
    "PiperConnectionError",
    "PiperEnableTimeoutError",
    "PiperError",
    "PiperNoFeedbackError",
    "clamp_targets",
]

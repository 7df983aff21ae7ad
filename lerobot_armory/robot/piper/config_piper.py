"""Configuration of the AgileX PiPER adapter (``--robot.type=piper``).

This module is imported by the armory client only to *register* the ``piper`` robot type with
LeRobot's config registry, so it must import cleanly on machines without ``piper_sdk`` or
``python-can``: neither is imported here (the robot imports them in ``connect()``).

Units used everywhere in the adapter (observations, actions, limits):

- joints ``joint_1.pos`` … ``joint_6.pos``: **degrees** (the SDK speaks 0.001°);
- gripper ``gripper.pos``: opening in **millimetres** (the SDK speaks 0.001 mm);
- gripper effort: **N·m** (the SDK speaks 0.001 N·m, range 0–5000).
"""

import math
from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig

from lerobot_armory.errors import ConfigError

# Registering the camera config types LeRobot ships makes `--robot.cameras='{"wrist": {"type":
# "opencv", ...}}'` parse without the caller having to import them first (LeRobot's own scripts
# do the same). Both modules are pure Python (no camera driver is loaded here).
try:  # pragma: no cover - the imports only fail on a broken LeRobot install
    from lerobot.cameras.opencv.configuration_opencv import OpenCVCameraConfig  # noqa: F401
    from lerobot.cameras.realsense.configuration_realsense import RealSenseCameraConfig  # noqa: F401
except ImportError:  # pragma: no cover
    pass

#: Joint names, in the order the SDK's ``JointCtrl`` takes them.
JOINT_NAMES: tuple[str, ...] = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6")
#: Every motor name the adapter exposes (``<name>.pos`` are the feature keys).
MOTOR_NAMES: tuple[str, ...] = (*JOINT_NAMES, "gripper")

#: Joint limits in degrees, from piper_sdk's ``JointCtrl`` documentation (AgileX PiPER).
JOINT_LIMITS_DEG: dict[str, tuple[float, float]] = {
    "joint_1": (-150.0, 150.0),
    "joint_2": (0.0, 180.0),
    "joint_3": (-170.0, 0.0),
    "joint_4": (-100.0, 100.0),
    "joint_5": (-70.0, 70.0),
    "joint_6": (-120.0, 120.0),
}
#: Gripper opening range in millimetres (standard PiPER gripper).
GRIPPER_RANGE_MM: tuple[float, float] = (0.0, 70.0)
#: Largest gripper effort the SDK accepts, in N·m (``GripperCtrl`` takes 0–5000 × 0.001 N·m).
GRIPPER_EFFORT_MAX_NM: float = 5.0


def _finite_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@RobotConfig.register_subclass("piper")
@dataclass
class PiperConfig(RobotConfig):
    """An AgileX PiPER 6-DoF arm with its parallel gripper, driven over CAN through ``piper_sdk``.

    Attributes:
        can_port: CAN interface name (``can0``; for python-can's ``virtual`` bus any channel name).
            piper_sdk keeps one interface object per name, so two robots need two ports.
        can_bustype: python-can interface. ``socketcan`` for the usual USB-CAN adapter on Linux
            (the port is then checked to exist, be up and run at 1 Mbit/s); tests use ``virtual``.
        cameras: LeRobot camera configs by name (``opencv``, ``intelrealsense``, ...); each adds an
            observation ``name: (height, width, 3)``.
        max_relative_target: largest move per ``send_action`` call, measured from the *present*
            position: a number applies to every motor (degrees for the joints, millimetres for the
            gripper); a dict ``{"joint_1": 5.0, "gripper": 10.0}`` sets it per motor and leaves the
            motors it does not name uncapped. ``None`` (default): no per-step cap, only the joint
            limits. At 30 fps, 5 caps a joint at 150 °/s.
        speed_ratio: percentage (1–100) of the arm's maximum speed for its joint moves (MOVE J),
            sent with every command (``MotionCtrl_2``).
        gripper_effort: gripper force limit in N·m (0–5; sent to the SDK as 0.001 N·m integers).
        disable_on_disconnect: disable the motors when disconnecting. Disabling **cuts motor power:
            the arm falls** under gravity unless it rests on something. The default (False) leaves
            the arm enabled, holding its last commanded position.
        enable_timeout_s: how long ``connect()`` keeps asking the arm to enable before giving up.
        feedback_timeout_s: how long ``connect()`` then waits for the first joint and gripper
            feedback; if none arrives it logs a warning and ``get_observation``/``send_action``
            raise until it does.
        feedback_grace_s: how long a feedback stream may read no frames before it counts as lost
            and nothing more is sent. piper_sdk's rate reads 0 for any 0.1 s window without a
            frame, which a stalled Python process can cause while the arm is fine; with the
            default a stopped arm is noticed within about 0.5 s. 0: trust the SDK's window alone.
    """

    can_port: str = "can0"
    can_bustype: str = "socketcan"
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    max_relative_target: float | dict[str, float] | None = None
    speed_ratio: int = 50
    gripper_effort: float = 1.0
    disable_on_disconnect: bool = False
    enable_timeout_s: float = 5.0
    feedback_timeout_s: float = 1.0
    feedback_grace_s: float = 0.3

    def __post_init__(self) -> None:
        super().__post_init__()  # LeRobot checks camera width/height/fps
        if not isinstance(self.can_port, str) or not self.can_port.strip():
            raise ConfigError("robot.can_port", f"must name a CAN interface such as 'can0', got {self.can_port!r}")
        if not isinstance(self.can_bustype, str) or not self.can_bustype.strip():
            raise ConfigError(
                "robot.can_bustype",
                f"must name a python-can interface ('socketcan', 'slcan', 'virtual', ...), got {self.can_bustype!r}",
            )
        if isinstance(self.speed_ratio, bool) or not isinstance(self.speed_ratio, int):
            raise ConfigError("robot.speed_ratio", f"must be an integer percentage, got {self.speed_ratio!r}")
        if not 1 <= self.speed_ratio <= 100:
            # 0 is a valid byte for the SDK but the arm would never move: almost surely a mistake.
            raise ConfigError("robot.speed_ratio", f"must be in 1..100 (percent of full speed), got {self.speed_ratio}")
        if not _finite_number(self.gripper_effort) or not 0.0 <= self.gripper_effort <= GRIPPER_EFFORT_MAX_NM:
            raise ConfigError(
                "robot.gripper_effort",
                f"must be a force limit in N·m within [0, {GRIPPER_EFFORT_MAX_NM}], got {self.gripper_effort!r}",
            )
        self.gripper_effort = float(self.gripper_effort)
        self.max_relative_target = self._checked_max_relative_target(self.max_relative_target)
        if not isinstance(self.disable_on_disconnect, bool):
            raise ConfigError("robot.disable_on_disconnect", f"must be true or false, got {self.disable_on_disconnect!r}")
        if not _finite_number(self.enable_timeout_s) or self.enable_timeout_s <= 0:
            raise ConfigError("robot.enable_timeout_s", f"must be a positive number of seconds, got {self.enable_timeout_s!r}")
        if not _finite_number(self.feedback_timeout_s) or self.feedback_timeout_s < 0:
            raise ConfigError(
                "robot.feedback_timeout_s", f"must be a non-negative number of seconds, got {self.feedback_timeout_s!r}"
            )
        if not _finite_number(self.feedback_grace_s) or not 0 <= self.feedback_grace_s <= 2.0:
            # More than a couple of seconds would clamp targets against a badly stale position.
            raise ConfigError(
                "robot.feedback_grace_s", f"must be a number of seconds within [0, 2], got {self.feedback_grace_s!r}"
            )

    @staticmethod
    def _checked_max_relative_target(value: object) -> float | dict[str, float] | None:
        """Validate ``max_relative_target`` and normalise numbers to float."""
        field_name = "robot.max_relative_target"
        if value is None:
            return None
        if isinstance(value, dict):
            unknown = sorted(set(value) - set(MOTOR_NAMES))
            if unknown:
                raise ConfigError(field_name, f"unknown motor(s) {unknown}; known motors: {list(MOTOR_NAMES)}")
            out: dict[str, float] = {}
            for name, cap in value.items():
                if not _finite_number(cap) or cap <= 0:
                    raise ConfigError(f"{field_name}.{name}", f"must be a positive number, got {cap!r}")
                out[name] = float(cap)
            return out
        if not _finite_number(value) or value <= 0:  # type: ignore[operator]
            raise ConfigError(
                field_name, f"must be a positive number (degrees / mm per step), a per-motor dict or None, got {value!r}"
            )
        return float(value)  # type: ignore[arg-type]

    def relative_caps(self) -> dict[str, float | None]:
        """The per-step cap of every motor (degrees for joints, mm for the gripper; None: uncapped)."""
        cap = self.max_relative_target
        if cap is None:
            return dict.fromkeys(MOTOR_NAMES, None)
        if isinstance(cap, dict):
            return {name: cap.get(name) for name in MOTOR_NAMES}
        return dict.fromkeys(MOTOR_NAMES, cap)

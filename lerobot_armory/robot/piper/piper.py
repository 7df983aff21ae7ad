"""LeRobot ``Robot`` for the AgileX PiPER arm, over CAN through ``piper_sdk`` (``C_PiperInterface_V2``).

Observations and actions are the same seven floats, in physical units:
``joint_1.pos`` … ``joint_6.pos`` in degrees and ``gripper.pos`` (opening) in millimetres, plus
one ``(height, width, 3)`` image per configured camera.

Safety behaviour, in one place:

- ``connect()`` asks the arm to enable until it reports all six joint drivers enabled, or gives
  up after ``enable_timeout_s`` and releases everything it opened.
- Nothing is sent to the motors while the arm's feedback is missing: it never arrived, or
  piper_sdk's feedback rate has read 0 for longer than ``feedback_grace_s`` (the rate reads 0
  for any 0.1 s window without a frame, so a stopped arm is noticed within about
  ``0.2 s + feedback_grace_s``; the grace keeps one late frame from halting a healthy arm).
- Every target is clamped to the documented joint limits and gripper range, then to
  ``present ± max_relative_target``.
- ``disconnect()`` is idempotent and safe after a failed ``connect()`` (the client calls it in a
  ``finally`` block, e.g. after Ctrl-C). By default it leaves the arm enabled, holding its last
  position; with ``disable_on_disconnect`` it disables the motors, which cuts their power.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from functools import cached_property
from types import ModuleType
from typing import TYPE_CHECKING, Any

from lerobot.cameras import make_cameras_from_configs
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from .config_piper import GRIPPER_RANGE_MM, JOINT_LIMITS_DEG, JOINT_NAMES, MOTOR_NAMES, PiperConfig

if TYPE_CHECKING:  # piper_sdk is optional: imported lazily in connect()
    from piper_sdk import C_PiperInterface_V2

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'lerobot-armory[piper]'"
CAN_SETUP_HINT = (
    "check that the arm is powered and the USB-CAN adapter is plugged in, and bring the port up at "
    "1 Mbit/s: `sudo ip link set {port} up type can bitrate 1000000` (see docs/piper.md)"
)

# piper_sdk constants (MotionCtrl_2 / GripperCtrl / EnableArm arguments).
CTRL_MODE_CAN = 0x01  # take commands from the CAN bus
MOVE_MODE_J = 0x01  # MOVE J: joint-space moves to JointCtrl targets
MIT_MODE_OFF = 0x00  # position-velocity mode (not MIT)
GRIPPER_ENABLE = 0x01
GRIPPER_DISABLE = 0x00
CAN_BITRATE = 1_000_000

# The SDK's reader thread polls with recv(timeout=1 s) and only notices DisconnectPort() after that
# poll returns; reconnecting the same (singleton) interface before it has exited would leave the
# new connection without a reader. Waiting this long after our own disconnect avoids the race.
SDK_READER_EXIT_S = 1.2
ENABLE_POLL_S = 0.05
FEEDBACK_POLL_S = 0.02
DISABLE_TIMEOUT_S = 1.0

# CAN ports driven by a live Piper in this process (piper_sdk hands out one object per port name,
# so two Piper objects on one port would silently share, and fight over, one arm).
_ports_lock = threading.Lock()
_ports_in_use: set[str] = set()
_last_release: dict[str, float] = {}


class PiperError(RuntimeError):
    """Base class of the PiPER adapter's errors."""


class PiperConnectionError(PiperError, ConnectionError):
    """The CAN port could not be opened, or the arm does not answer on it."""


class PiperEnableTimeoutError(PiperError, TimeoutError):
    """The arm answers on the bus but did not report enabled within ``enable_timeout_s``."""


class PiperNoFeedbackError(PiperError):
    """No joint/gripper feedback from the arm (none yet, or it stopped): nothing is sent."""


def _import_sdk() -> ModuleType:
    """Import piper_sdk, or explain how to install it."""
    try:
        import piper_sdk
    except ImportError as e:
        raise ImportError(f"the PiPER adapter needs piper_sdk and python-can: {INSTALL_HINT}") from e
    return piper_sdk


def _clamp(value: float, low: float, high: float) -> float:
    return max(low, min(value, high))


def clamp_targets(
    goal: Mapping[str, float], present: Mapping[str, float], caps: Mapping[str, float | None]
) -> dict[str, float]:
    """Safe targets for every motor in ``MOTOR_NAMES`` (degrees / mm).

    Each goal is clamped to its joint limits (gripper: ``GRIPPER_RANGE_MM``), then to
    ``present ± cap`` when the motor has a cap. The cap is applied last on purpose: if the arm
    sits outside its limits it is walked back in by at most ``cap`` per step rather than jumping.
    """
    safe: dict[str, float] = {}
    for name in MOTOR_NAMES:
        low, high = GRIPPER_RANGE_MM if name == "gripper" else JOINT_LIMITS_DEG[name]
        target = _clamp(goal[name], low, high)
        cap = caps.get(name)
        if cap is not None:
            target = _clamp(target, present[name] - cap, present[name] + cap)
        safe[name] = target
    return safe


class Piper(Robot):
    """An AgileX PiPER arm (6 joints + gripper) as a LeRobot robot.

    Built by ``make_robot_from_config(PiperConfig(...))`` or ``--robot.type=piper``.
    See :mod:`lerobot_armory.robot.piper.piper` for units and safety behaviour.
    """

    config_class = PiperConfig
    name = "piper"

    def __init__(self, config: PiperConfig) -> None:
        super().__init__(config)
        self.config = config
        self.cameras = make_cameras_from_configs(config.cameras)
        self._arm: C_PiperInterface_V2 | None = None
        self._connected = False
        self._port_claimed = False
        # Serialises send_action against disconnect so no frame goes out once disconnect began.
        self._lock = threading.RLock()
        self._closing = False
        # Feedback freshness: when each stream last read a non-zero rate, on an injectable clock.
        self._clock: Callable[[], float] = time.monotonic
        self._feedback_seen: dict[str, float] = {}

    # ------------------------------------------------------------------ features

    @cached_property
    def _motors_ft(self) -> dict[str, type]:
        return {f"{name}.pos": float for name in MOTOR_NAMES}

    @cached_property
    def _cameras_ft(self) -> dict[str, tuple[int, int, int]]:
        features: dict[str, tuple[int, int, int]] = {}
        for name, cam in self.cameras.items():
            if getattr(cam, "use_rgb", True):
                features[name] = (cam.height, cam.width, 3)
            if getattr(cam, "use_depth", False):
                features[f"{name}_depth"] = (cam.height, cam.width, 1)
        return features

    @cached_property
    def observation_features(self) -> dict[str, type | tuple[int, int, int]]:
        """``joint_1.pos`` … ``joint_6.pos`` (degrees), ``gripper.pos`` (mm), cameras ``(h, w, 3)``."""
        return {**self._motors_ft, **self._cameras_ft}

    @cached_property
    def action_features(self) -> dict[str, type]:
        """The seven targets: ``joint_1.pos`` … ``joint_6.pos`` (degrees) and ``gripper.pos`` (mm)."""
        return dict(self._motors_ft)

    # ------------------------------------------------------------------ connection

    @property
    def is_connected(self) -> bool:
        """True once the arm is enabled and every camera is open, until ``disconnect()``."""
        return self._connected and self._arm is not None and all(cam.is_connected for cam in self.cameras.values())

    @property
    def is_calibrated(self) -> bool:
        """Always True: the PiPER reports calibrated joint angles itself (zeroed at the factory)."""
        return True

    def calibrate(self) -> None:
        """No-op: the arm's joint zeros live in its firmware (re-zeroing is a piper_sdk tool job)."""

    def configure(self) -> None:
        """No-op: the control mode and speed ratio are sent with every command (``MotionCtrl_2``)."""

    def connect(self, calibrate: bool = True) -> None:
        """Open the CAN port, enable the arm, wait for its feedback, then open the cameras.

        Args:
            calibrate: ignored (the PiPER needs no calibration; kept for LeRobot's interface).

        Raises:
            DeviceAlreadyConnectedError: this robot, or another Piper in this process, uses the port.
            ImportError: piper_sdk is not installed.
            PiperConnectionError: the port cannot be opened or the arm sends no feedback.
            PiperEnableTimeoutError: the arm did not report enabled within ``enable_timeout_s``.

        On any failure (Ctrl-C included) everything opened so far is released again.
        """
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected.")
        sdk = _import_sdk()
        try:
            self._open_port(sdk)
            self._enable()
            self._wait_for_feedback()
            for cam in self.cameras.values():
                cam.connect()
            self.configure()
            self._connected = True
        except BaseException:
            # BaseException: a Ctrl-C in the enable loop must release the bus too.
            self._release()
            raise
        log.info("%s connected on %s (%s).", self, self.config.can_port, self.config.can_bustype)

    def _open_port(self, sdk: ModuleType) -> None:
        port = self.config.can_port
        with _ports_lock:
            if port in _ports_in_use:
                raise DeviceAlreadyConnectedError(f"CAN port {port!r} is already driven by another Piper in this process.")
            _ports_in_use.add(port)
            self._port_claimed = True
            wait = _last_release.get(port, -math.inf) + SDK_READER_EXIT_S - time.monotonic()
        if wait > 0:
            time.sleep(wait)

        # The SDK's own port check (exists, up, 1 Mbit/s) only makes sense for socketcan.
        judge = self.config.can_bustype == "socketcan"
        # One object per port name: reused (and re-opened) on reconnect.
        arm = sdk.C_PiperInterface_V2(can_name=port, judge_flag=judge, can_auto_init=False)
        if arm.get_connect_status():
            raise DeviceAlreadyConnectedError(
                f"piper_sdk's interface for {port!r} is already connected by other code in this process."
            )
        self._arm = arm
        try:
            arm.CreateCanBus(port, bustype=self.config.can_bustype, expected_bitrate=CAN_BITRATE, judge_flag=judge)
        except ConnectionError as e:
            # The SDK replaces the real reason by "CreateCanBus ERROR"; it survives as __context__.
            reason = e.__context__ or e
            raise PiperConnectionError(
                f"cannot open CAN port {port!r} ({self.config.can_bustype}): {reason}; {CAN_SETUP_HINT.format(port=port)}"
            ) from e
        can_bus = arm.GetCanBus()
        if can_bus is None or getattr(can_bus, "recv_bus", None) is None or getattr(can_bus, "send_bus", None) is None:
            # python-can errors inside the SDK are swallowed and leave the bus unset.
            raise PiperConnectionError(
                f"cannot open CAN port {port!r} ({self.config.can_bustype}); {CAN_SETUP_HINT.format(port=port)}"
            )
        arm.ConnectPort()  # starts the SDK's reader thread

    def _enable(self) -> None:
        """Ask for enable until the arm reports all joint drivers enabled, or time out."""
        arm = self._require_arm()
        deadline = time.monotonic() + self.config.enable_timeout_s
        stale_stamp = arm.GetArmLowSpdInfoMsgs().time_stamp  # driver-status cache before we start
        fresh_since: float | None = None
        while True:
            now = time.monotonic()
            if fresh_since is None and arm.GetArmLowSpdInfoMsgs().time_stamp != stale_stamp:
                fresh_since = now
            # EnablePiper() sends EnableArm(7) and returns the state read *before* sending: True
            # means a previous request took effect. Statuses are only trusted once driver frames
            # have been arriving for a poll period (the SDK's cache may hold a previous session's).
            was_enabled = arm.EnablePiper()
            if was_enabled and fresh_since is not None and now - fresh_since >= ENABLE_POLL_S:
                log.debug("PiPER on %s enabled.", self.config.can_port)
                return
            if now >= deadline:
                break
            time.sleep(ENABLE_POLL_S)
        port = self.config.can_port
        if fresh_since is None:
            raise PiperConnectionError(
                f"no feedback from a PiPER on {port!r} within {self.config.enable_timeout_s} s; "
                + CAN_SETUP_HINT.format(port=port)
            )
        raise PiperEnableTimeoutError(
            f"the PiPER on {port!r} did not report enabled within {self.config.enable_timeout_s} s "
            f"(joint drivers enabled: {arm.GetArmEnableStatus()}); check the emergency stop, that the arm is "
            "not in teach mode or in a fault state (power-cycle it), and raise --robot.enable_timeout_s if it "
            "is just slow"
        )

    def _wait_for_feedback(self) -> None:
        deadline = time.monotonic() + self.config.feedback_timeout_s
        while self._missing_feedback():
            if time.monotonic() >= deadline:
                log.warning(
                    "PiPER on %s is enabled but sends no %s feedback yet; observations and actions will "
                    "raise until it does.",
                    self.config.can_port,
                    " or ".join(self._missing_feedback()),
                )
                return
            time.sleep(FEEDBACK_POLL_S)

    def _missing_feedback(self) -> list[str]:
        """Which feedback streams are silent: never seen, or no frames for ``feedback_grace_s``.

        The SDK's rate (``Hz``) is 0 until the first frame and for any 0.1 s window without one.
        A real arm streams at ~200 Hz, but a Python process stalled ~0.1 s (GIL, GC, a busy
        machine) can see one empty window while the arm is fine; refusing to move then would
        halt a healthy robot. So a stream counts as lost only once its rate has read 0 for
        longer than the grace, measured from the last read that saw frames.
        """
        arm = self._require_arm()
        now = self._clock()
        rates = {
            "joint": arm.GetArmJointMsgs().Hz,  # 0 unless all three joint frames arrive
            "gripper": arm.GetArmGripperMsgs().Hz,
        }
        missing = []
        for stream, hz in rates.items():
            if hz > 0:
                self._feedback_seen[stream] = now
                continue
            seen = self._feedback_seen.get(stream)
            if seen is None or now - seen > self.config.feedback_grace_s:
                missing.append(stream)
        return missing

    def _require_arm(self) -> C_PiperInterface_V2:
        if self._arm is None:
            raise DeviceNotConnectedError(f"{self} is not connected. Run `.connect()` first.")
        return self._arm

    # ------------------------------------------------------------------ state and commands

    def _present(self) -> dict[str, float]:
        """Present joint angles (degrees) and gripper opening (mm); raises without fresh feedback."""
        arm = self._require_arm()
        missing = self._missing_feedback()
        if missing:
            raise PiperNoFeedbackError(
                f"no {' or '.join(missing)} feedback from the PiPER on {self.config.can_port!r} (none received yet, "
                "or it stopped); refusing to read or move. Check the arm's power and CAN wiring."
            )
        joints = arm.GetArmJointMsgs().joint_state
        gripper = arm.GetArmGripperMsgs().gripper_state
        present = {name: getattr(joints, name) / 1000.0 for name in JOINT_NAMES}  # 0.001° -> °
        present["gripper"] = gripper.grippers_angle / 1000.0  # 0.001 mm -> mm
        return present

    def get_observation(self) -> dict[str, Any]:
        """Joint angles (°), gripper opening (mm) and the latest camera frames.

        Raises:
            DeviceNotConnectedError: before ``connect()``.
            PiperNoFeedbackError: the arm's feedback never arrived or stopped.
        """
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected. Run `.connect()` first.")
        obs: dict[str, Any] = {f"{name}.pos": value for name, value in self._present().items()}
        for name, cam in self.cameras.items():
            if getattr(cam, "use_rgb", True):
                obs[name] = cam.read_latest()
            if getattr(cam, "use_depth", False):
                obs[f"{name}_depth"] = cam.read_latest_depth()
        return obs

    def _goal(self, action: Mapping[str, Any]) -> dict[str, float]:
        goal: dict[str, float] = {}
        missing = [f"{name}.pos" for name in MOTOR_NAMES if f"{name}.pos" not in action]
        if missing:
            raise ValueError(f"PiPER action lacks {missing}; it needs all of {list(self.action_features)}")
        for name in MOTOR_NAMES:
            value = float(action[f"{name}.pos"])
            if not math.isfinite(value):
                # A NaN would slip through min/max clamping; never send it.
                raise ValueError(f"PiPER action {name}.pos is not finite: {value}")
            goal[name] = value
        return goal

    def send_action(self, action: Mapping[str, Any]) -> dict[str, float]:
        """Move towards the target joint angles (°) and gripper opening (mm).

        Each target is clamped to the joint limits (gripper: 0–70 mm), then to
        ``present ± max_relative_target``, rounded to the SDK's 0.001 units and sent as
        ``MotionCtrl_2`` (CAN control, MOVE J, ``speed_ratio``), ``JointCtrl`` and ``GripperCtrl``.

        Returns:
            The action actually sent (after clamping and rounding), same keys and units.

        Raises:
            DeviceNotConnectedError: before ``connect()`` or once ``disconnect()`` began.
            PiperNoFeedbackError: no fresh feedback, so no safe reference to clamp against.
            ValueError: a key is missing or a value is not finite.
        """
        with self._lock:
            if not self.is_connected or self._closing:
                raise DeviceNotConnectedError(f"{self} is not connected. Run `.connect()` first.")
            arm = self._require_arm()
            goal = self._goal(action)
            present = self._present()
            sent = clamp_targets(goal, present, self.config.relative_caps())
            units = {name: round(value * 1000.0) for name, value in sent.items()}  # -> 0.001° / 0.001 mm
            if any(abs(sent[n] - goal[n]) > 1e-6 for n in MOTOR_NAMES):
                log.debug("PiPER action clamped: asked %s, sending %s", goal, sent)
            arm.MotionCtrl_2(CTRL_MODE_CAN, MOVE_MODE_J, self.config.speed_ratio, MIT_MODE_OFF)
            arm.JointCtrl(*(units[name] for name in JOINT_NAMES))
            arm.GripperCtrl(units["gripper"], round(self.config.gripper_effort * 1000.0), GRIPPER_ENABLE, 0)
        return {f"{name}.pos": units[name] / 1000.0 for name in MOTOR_NAMES}

    # ------------------------------------------------------------------ shutdown

    def disconnect(self) -> None:
        """Stop sending, optionally disable the motors, close the cameras and the CAN port.

        Idempotent and safe after a failed ``connect()``; errors are logged, not raised, so that a
        ``finally: robot.disconnect()`` never hides the exception that got there. With
        ``disable_on_disconnect`` the motors (and gripper) are disabled first: **the arm loses
        power and drops**. Otherwise the arm stays enabled, holding its last commanded position.
        """
        if self._release():
            log.info("%s disconnected.", self)

    def _release(self) -> bool:
        """Undo whatever connect() did; returns whether there was anything to undo."""
        with self._lock:
            self._closing = True  # no send_action gets through from here on
            arm = self._arm
            try:
                if arm is not None and self.config.disable_on_disconnect and arm.get_connect_status():
                    try:
                        self._disable(arm)
                    except Exception:
                        log.exception("Could not disable the PiPER on %s.", self.config.can_port)
                for name, cam in self.cameras.items():
                    try:
                        if cam.is_connected:
                            cam.disconnect()
                    except Exception:
                        log.exception("Could not disconnect camera %r.", name)
            finally:
                # In `finally` so that even a second Ctrl-C during the above closes the port.
                try:
                    if arm is not None:
                        self._close_port(arm)
                finally:
                    self._arm = None
                    self._feedback_seen.clear()  # a new connection must see fresh frames again
                    self._connected = False
                    self._closing = False
                    if self._port_claimed:
                        with _ports_lock:
                            _ports_in_use.discard(self.config.can_port)
                            _last_release[self.config.can_port] = time.monotonic()
                        self._port_claimed = False
        return arm is not None

    def _disable(self, arm: C_PiperInterface_V2) -> None:
        """Disable all motors and the gripper; confirm from the driver status frames."""
        try:
            gripper_mm = arm.GetArmGripperMsgs().gripper_state.grippers_angle
        except Exception:
            gripper_mm = 0
        deadline = time.monotonic() + DISABLE_TIMEOUT_S
        while True:
            arm.DisablePiper()
            arm.GripperCtrl(gripper_mm, 0, GRIPPER_DISABLE, 0)
            time.sleep(ENABLE_POLL_S)
            if not any(arm.GetArmEnableStatus()):
                log.info("PiPER on %s disabled (motors unpowered).", self.config.can_port)
                return
            if time.monotonic() >= deadline:
                log.error("PiPER on %s did not confirm it is disabled.", self.config.can_port)
                return

    def _close_port(self, arm: C_PiperInterface_V2) -> None:
        try:
            if arm.get_connect_status():
                arm.DisconnectPort()  # stops the reader and closes the buses
            else:
                can_bus = arm.GetCanBus()  # CreateCanBus may have opened buses before a failure
                if can_bus is not None:
                    can_bus.Close()
        except Exception:
            log.exception("Could not close CAN port %s.", self.config.can_port)

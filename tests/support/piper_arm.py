"""A fake AgileX PiPER on python-can's ``virtual`` bus, for testing the adapter without hardware.

It speaks the arm's side of the CAN protocol (as decoded by piper_sdk 0.6):

- feedback it sends every ``period_s``: joint angles 0x2A5–0x2A7 (two big-endian int32 in 0.001°
  per frame), gripper 0x2A8 (``>iHBB``: opening in 0.001 mm, effort in 0.001 N·m, status,
  reserved) and the low-speed driver frames 0x261–0x266 (``>HhbBH``; status bit 6 = enabled);
- commands it records and obeys: EnableArm/DisableArm 0x471 (``[motor, 0x02 enable | 0x01
  disable]``), MotionCtrl_2 0x151, JointCtrl 0x155–0x157 and GripperCtrl 0x159. While enabled and
  in CAN control + MOVE J, its reported joints move toward the commanded targets at
  ``speed_mdeg_per_tick`` (and the gripper at ``speed_um_per_tick``).

Knobs for failure cases: ``send_feedback=False`` (a silent arm), ``send_joint_feedback=False``
(driver frames only: it can enable but reports no joints/gripper), ``never_enable=True`` (answers,
but ignores enable requests), and :meth:`pause_feedback` to stop feedback mid-run.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import can

JOINT_FEEDBACK_IDS = (0x2A5, 0x2A6, 0x2A7)
GRIPPER_FEEDBACK_ID = 0x2A8
LOW_SPEED_IDS = tuple(range(0x261, 0x267))
MOTION_CTRL_2_ID = 0x151
JOINT_CTRL_IDS = (0x155, 0x156, 0x157)
GRIPPER_CTRL_ID = 0x159
ENABLE_ID = 0x471

ENABLE_BIT = 0x40  # bit 6 of the driver status byte
ENABLE_FLAG = 0x02
DISABLE_FLAG = 0x01


@dataclass
class MotionCtrl:
    """A decoded MotionCtrl_2 (0x151) frame."""

    ctrl_mode: int
    move_mode: int
    speed_ratio: int
    mit_mode: int


@dataclass
class GripperCmd:
    """A decoded GripperCtrl (0x159) frame (opening in 0.001 mm, effort in 0.001 N·m)."""

    angle: int
    effort: int
    code: int
    set_zero: int


@dataclass
class Recorded:
    """Everything the fake arm received, in arrival order."""

    frames: list[tuple[int, bytes]] = field(default_factory=list)
    enables: list[tuple[int, int]] = field(default_factory=list)  # (motor, flag)
    motion: list[MotionCtrl] = field(default_factory=list)
    joint_frames: list[tuple[int, int, int]] = field(default_factory=list)  # (can id, a, b) in 0.001°
    gripper: list[GripperCmd] = field(default_factory=list)


class FakePiperArm:
    """A PiPER that lives on ``can.Bus(interface="virtual", channel=channel)``, run in a thread.

    Args:
        channel: virtual bus channel (use a unique name per test).
        joints_mdeg: initial joint angles in 0.001°.
        gripper_um: initial gripper opening in 0.001 mm.
        send_feedback: send any feedback at all.
        send_joint_feedback: send joint and gripper feedback (driver frames are separate).
        never_enable: ignore enable requests (drivers always report disabled).
        enabled: start enabled (as an arm left enabled by a previous session).
        period_s: feedback period (the real arm streams at ~200 Hz; the SDK's rate counter needs a
            frame in every 0.1 s window).
        speed_mdeg_per_tick / speed_um_per_tick: how far the joints / gripper move per period.
    """

    def __init__(
        self,
        channel: str,
        *,
        joints_mdeg: Sequence[int] = (0, 0, 0, 0, 0, 0),
        gripper_um: int = 0,
        send_feedback: bool = True,
        send_joint_feedback: bool = True,
        never_enable: bool = False,
        enabled: bool = False,
        period_s: float = 0.01,
        speed_mdeg_per_tick: int = 2_000,
        speed_um_per_tick: int = 2_000,
    ) -> None:
        if len(joints_mdeg) != 6:
            raise ValueError("joints_mdeg needs 6 values")
        self.channel = channel
        self.send_feedback = send_feedback
        self.send_joint_feedback = send_joint_feedback
        self.never_enable = never_enable
        self.period_s = period_s
        self.speed_mdeg_per_tick = speed_mdeg_per_tick
        self.speed_um_per_tick = speed_um_per_tick
        self._lock = threading.Lock()
        self._joints = [int(v) for v in joints_mdeg]
        self._gripper = int(gripper_um)
        self._joint_target: list[int] | None = None
        self._gripper_target: int | None = None
        self._enabled = enabled and not never_enable
        self._gripper_enabled = False
        self._mode: MotionCtrl | None = None
        self._paused = False
        self.recorded = Recorded()
        self._stop = threading.Event()
        self._bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self._thread = threading.Thread(target=self._run, name=f"FakePiperArm({channel})", daemon=True)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> FakePiperArm:
        """Start answering on the bus; returns self."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the bus."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._bus.shutdown()

    def __enter__(self) -> FakePiperArm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ inspection

    @property
    def enabled(self) -> bool:
        with self._lock:
            return self._enabled

    @property
    def joints_mdeg(self) -> list[int]:
        with self._lock:
            return list(self._joints)

    @property
    def gripper_um(self) -> int:
        with self._lock:
            return self._gripper

    def set_joints(self, joints_mdeg: Sequence[int], gripper_um: int | None = None) -> None:
        """Teleport the reported state (e.g. to put a joint outside its limits)."""
        with self._lock:
            self._joints = [int(v) for v in joints_mdeg]
            if gripper_um is not None:
                self._gripper = int(gripper_um)

    def pause_feedback(self, paused: bool = True) -> None:
        """Stop (or resume) all feedback, as if the arm's CAN cable came loose."""
        with self._lock:
            self._paused = paused

    def snapshot(self) -> Recorded:
        """A copy of what was received so far."""
        with self._lock:
            r = self.recorded
            return Recorded(list(r.frames), list(r.enables), list(r.motion), list(r.joint_frames), list(r.gripper))

    def wait_for(self, predicate: Callable[[FakePiperArm], bool], timeout: float = 2.0) -> bool:
        """Poll ``predicate(self)`` until true or ``timeout``; returns the last value."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.01)
        return predicate(self)

    # ------------------------------------------------------------------ the arm

    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_tick:  # ticks first, so a stream of commands cannot starve feedback
                self._tick()
                next_tick += self.period_s
                if next_tick < now:  # fell behind (slow CI): don't burst
                    next_tick = now + self.period_s
                continue
            try:
                msg = self._bus.recv(timeout=next_tick - now)
            except can.CanError:
                return
            if msg is not None:
                self._handle(msg)

    def _handle(self, msg: can.Message) -> None:
        data = bytes(msg.data)
        can_id = msg.arbitration_id
        with self._lock:
            self.recorded.frames.append((can_id, data))
            if can_id == ENABLE_ID:
                motor, flag = data[0], data[1]
                self.recorded.enables.append((motor, flag))
                if motor in (7, 0xFF):
                    if flag == ENABLE_FLAG and not self.never_enable:
                        self._enabled = True
                    elif flag == DISABLE_FLAG:
                        self._enabled = False
                        self._joint_target = None  # an unpowered arm forgets its goal
            elif can_id == MOTION_CTRL_2_ID:
                mode = MotionCtrl(data[0], data[1], data[2], data[3])
                self.recorded.motion.append(mode)
                self._mode = mode
            elif can_id in JOINT_CTRL_IDS:
                a, b = struct.unpack(">ii", data)
                self.recorded.joint_frames.append((can_id, a, b))
                k = 2 * JOINT_CTRL_IDS.index(can_id)
                target = list(self._joint_target or self._joints)
                target[k], target[k + 1] = a, b
                self._joint_target = target
            elif can_id == GRIPPER_CTRL_ID:
                angle, effort, code, set_zero = struct.unpack(">iHBB", data)
                self.recorded.gripper.append(GripperCmd(angle, effort, code, set_zero))
                self._gripper_enabled = code in (0x01, 0x03)
                self._gripper_target = angle if self._gripper_enabled else None

    def _tick(self) -> None:
        with self._lock:
            self._move()
            if not self.send_feedback or self._paused:
                return
            frames: list[tuple[int, bytes]] = []
            if self.send_joint_feedback:
                j = self._joints
                frames += [(JOINT_FEEDBACK_IDS[i], struct.pack(">ii", j[2 * i], j[2 * i + 1])) for i in range(3)]
                status = ENABLE_BIT if self._gripper_enabled else 0
                frames.append((GRIPPER_FEEDBACK_ID, struct.pack(">iHBB", self._gripper, 0, status, 0)))
            status = ENABLE_BIT if self._enabled else 0
            # 24.0 V, 30 °C driver, 25 °C motor, status, 0 A
            frames += [(can_id, struct.pack(">HhbBH", 240, 30, 25, status, 0)) for can_id in LOW_SPEED_IDS]
        for can_id, data in frames:
            try:
                self._bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
            except can.CanError:
                return

    def _move(self) -> None:
        """Step the reported state toward the targets (only when the arm would really move)."""
        mode = self._mode
        if self._enabled and self._joint_target is not None and mode and (mode.ctrl_mode, mode.move_mode) == (1, 1):
            for i, target in enumerate(self._joint_target):
                delta = max(-self.speed_mdeg_per_tick, min(target - self._joints[i], self.speed_mdeg_per_tick))
                self._joints[i] += delta
        if self._gripper_target is not None:
            delta = self._gripper_target - self._gripper
            self._gripper += max(-self.speed_um_per_tick, min(delta, self.speed_um_per_tick))

"""The PiPER adapter against a fake arm on python-can's ``virtual`` bus (no hardware).

Every test uses its own channel name: python-can's virtual buses and piper_sdk's one-interface-
per-name singletons are process-wide.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import draccus
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lerobot.robots.config import RobotConfig
from lerobot.robots.utils import make_robot_from_config
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from lerobot_armory.errors import ConfigError
from lerobot_armory.robot.piper import (
    GRIPPER_RANGE_MM,
    JOINT_LIMITS_DEG,
    MOTOR_NAMES,
    Piper,
    PiperConfig,
    PiperConnectionError,
    PiperEnableTimeoutError,
    PiperNoFeedbackError,
    clamp_targets,
)

try:  # the optional extra: without it only the config/clamping tests run
    import can  # noqa: F401
    import piper_sdk  # noqa: F401

    HAVE_SDK = True
except ImportError:
    HAVE_SDK = False
if HAVE_SDK:
    from tests.support.piper_arm import DISABLE_FLAG, ENABLE_FLAG, FakePiperArm, GripperCmd, MotionCtrl

# piper_sdk 0.6.2 still passes python-can's deprecated `bustype=`; not our warning to fix.
pytestmark = pytest.mark.filterwarnings("ignore:The 'bustype' argument is deprecated:DeprecationWarning")

# A pose with negative angles and sub-degree parts, in the arm's units (0.001° / 0.001 mm).
START_MDEG = (10_000, 45_500, -30_250, 5_000, -12_345, 90_000)
START_GRIPPER_UM = 35_000
START_DEG = dict(zip(MOTOR_NAMES, [v / 1000 for v in START_MDEG] + [START_GRIPPER_UM / 1000]))
KEYS = [f"{name}.pos" for name in MOTOR_NAMES]


def action(**overrides: float) -> dict[str, float]:
    """The START pose as an action, with some motors changed (``joint_1=20.0, gripper=5.0``)."""
    values = {**START_DEG, **overrides}
    return {f"{name}.pos": values[name] for name in MOTOR_NAMES}


def sdk_port_connected(channel: str) -> bool:
    from piper_sdk import C_PiperInterface_V2

    return C_PiperInterface_V2(can_name=channel, judge_flag=False, can_auto_init=False).get_connect_status()


class FakeCamera:
    """Duck-typed LeRobot camera: what Piper uses of one."""

    def __init__(self, height: int = 48, width: int = 64, fail_connect: bool = False) -> None:
        self.height, self.width = height, width
        self.fail_connect = fail_connect
        self.is_connected = False

    def connect(self, warmup: bool = True) -> None:
        if self.fail_connect:
            raise RuntimeError("camera unplugged")
        self.is_connected = True

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        return np.full((self.height, self.width, 3), 7, dtype=np.uint8)

    def disconnect(self) -> None:
        self.is_connected = False


@pytest.fixture
def channel() -> str:
    return f"piper-test-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def make_fake(channel):
    if not HAVE_SDK:
        pytest.skip("needs piper_sdk and python-can: pip install 'lerobot-armory[piper]'")
    fakes: list[FakePiperArm] = []

    def _make(**kwargs) -> FakePiperArm:
        kwargs.setdefault("joints_mdeg", START_MDEG)
        kwargs.setdefault("gripper_um", START_GRIPPER_UM)
        fake = FakePiperArm(channel, **kwargs).start()
        fakes.append(fake)
        return fake

    yield _make
    for fake in fakes:
        fake.stop()


@pytest.fixture
def make_robot(channel, tmp_path, make_fake):  # after make_fake: robots disconnect before fakes stop
    robots: list[Piper] = []

    def _make(**kwargs) -> Piper:
        kwargs.setdefault("can_port", channel)
        kwargs.setdefault("can_bustype", "virtual")
        kwargs.setdefault("calibration_dir", tmp_path / "calibration")
        # connect() returns at the first feedback frame; the long wait only matters when the
        # 2-core CI machine is busy and the fake arm's first frames are late.
        kwargs.setdefault("feedback_timeout_s", 10.0)
        robot = Piper(PiperConfig(**kwargs))
        robots.append(robot)
        return robot

    yield _make
    for robot in robots:
        robot.disconnect()


def has_feedback(robot: Piper) -> bool:
    try:
        robot.get_observation()
    except PiperNoFeedbackError:
        return False
    return True


def no_motion_commands(fake: FakePiperArm) -> bool:
    snap = fake.snapshot()
    return not snap.motion and not snap.joint_frames and not snap.gripper


# ---------------------------------------------------------------- connect and observe


def test_connect_enables_and_reads_degrees_and_mm(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot()
    robot.connect()
    assert robot.is_connected and robot.is_calibrated
    assert (7, ENABLE_FLAG) in fake.snapshot().enables and fake.enabled

    obs = robot.get_observation()
    assert list(obs) == KEYS == list(robot.observation_features)
    assert all(type(v) is float for v in obs.values())
    # 0.001° -> degrees, 0.001 mm -> mm
    assert obs == pytest.approx({f"{k}.pos": v for k, v in START_DEG.items()}, abs=1e-9)
    assert obs["joint_5.pos"] == pytest.approx(-12.345)
    # Connecting must not move anything.
    assert no_motion_commands(fake)


def test_features_without_connecting(make_robot):
    from lerobot.cameras.opencv import OpenCVCameraConfig

    robot = make_robot(cameras={"wrist": OpenCVCameraConfig(index_or_path=0, width=640, height=480, fps=30)})
    assert robot.action_features == dict.fromkeys(KEYS, float)
    assert robot.observation_features == {**dict.fromkeys(KEYS, float), "wrist": (480, 640, 3)}
    assert not robot.is_connected


def test_camera_frames_in_observation(make_fake, make_robot):
    make_fake()
    robot = make_robot()
    cam = FakeCamera()
    robot.cameras = {"wrist": cam}
    robot.connect()
    assert cam.is_connected
    obs = robot.get_observation()
    assert obs["wrist"].shape == (48, 64, 3) == robot.observation_features["wrist"]
    robot.disconnect()
    assert not cam.is_connected


def test_camera_failure_leaves_nothing_half_connected(make_fake, make_robot, channel):
    make_fake()
    robot = make_robot()
    robot.cameras = {"ok": FakeCamera(), "broken": FakeCamera(fail_connect=True)}
    with pytest.raises(RuntimeError, match="camera unplugged"):
        robot.connect()
    assert not robot.is_connected
    assert not robot.cameras["ok"].is_connected
    assert not sdk_port_connected(channel)


# ---------------------------------------------------------------- send_action


def test_send_action_clamps_to_joint_limits_and_sends_sdk_units(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot(speed_ratio=80, gripper_effort=2.5)
    robot.connect()
    sent = robot.send_action(
        action(joint_1=200.0, joint_2=-10.0, joint_3=50.0, joint_4=-180.0, joint_5=12.3456, joint_6=-500.0, gripper=100.0)
    )
    assert sent == {
        "joint_1.pos": 150.0,
        "joint_2.pos": 0.0,
        "joint_3.pos": 0.0,
        "joint_4.pos": -100.0,
        "joint_5.pos": 12.346,  # rounded to the SDK's 0.001°
        "joint_6.pos": -120.0,
        "gripper.pos": 70.0,
    }
    assert fake.wait_for(lambda f: len(f.snapshot().joint_frames) >= 3 and f.snapshot().gripper)
    snap = fake.snapshot()
    assert snap.motion == [MotionCtrl(ctrl_mode=0x01, move_mode=0x01, speed_ratio=80, mit_mode=0x00)]
    assert snap.joint_frames == [(0x155, 150_000, 0), (0x156, 0, -100_000), (0x157, 12_346, -120_000)]
    assert snap.gripper == [GripperCmd(angle=70_000, effort=2_500, code=0x01, set_zero=0)]
    # MotionCtrl_2 first, then the joints, then the gripper.
    order = [can_id for can_id, _ in snap.frames if can_id in (0x151, 0x155, 0x156, 0x157, 0x159)]
    assert order == [0x151, 0x155, 0x156, 0x157, 0x159]


def test_send_action_clamps_to_max_relative_target(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot(max_relative_target=5.0)
    robot.connect()
    sent = robot.send_action(action(joint_1=100.0, joint_2=0.0, joint_3=-30.0, joint_5=-100.0, gripper=0.0))
    assert sent == pytest.approx(
        {
            "joint_1.pos": 15.0,  # 10 + 5
            "joint_2.pos": 40.5,  # 45.5 - 5
            "joint_3.pos": -30.0,  # within 5 of -30.25: untouched
            "joint_4.pos": 5.0,
            "joint_5.pos": -17.345,  # limit -70 first, then -12.345 - 5
            "joint_6.pos": 90.0,
            "gripper.pos": 30.0,  # a number caps the gripper too, in mm
        },
        abs=1e-9,
    )
    assert fake.wait_for(lambda f: len(f.snapshot().joint_frames) >= 3 and f.snapshot().gripper)
    snap = fake.snapshot()
    assert snap.joint_frames == [(0x155, 15_000, 40_500), (0x156, -30_000, 5_000), (0x157, -17_345, 90_000)]
    assert snap.gripper[0].angle == 30_000


def test_per_motor_cap_walks_an_out_of_range_joint_back(make_fake, make_robot):
    fake = make_fake(joints_mdeg=(10_000, -8_000, -30_250, 5_000, -12_345, 90_000))  # joint_2 below 0°
    robot = make_robot(max_relative_target={"joint_2": 5.0})
    robot.connect()
    sent = robot.send_action(action(joint_1=100.0, joint_2=10.0))
    assert sent["joint_1.pos"] == 100.0  # not in the dict: uncapped
    assert sent["joint_2.pos"] == pytest.approx(-3.0)  # toward the range, by at most 5°
    assert fake.wait_for(lambda f: len(f.snapshot().joint_frames) >= 1)
    assert fake.snapshot().joint_frames[0] == (0x155, 100_000, -3_000)


def test_gripper_clamped_to_its_range(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot()
    robot.connect()
    assert robot.send_action(action(gripper=-5.0))["gripper.pos"] == 0.0
    assert robot.send_action(action(gripper=70.0001))["gripper.pos"] == 70.0
    assert robot.send_action(action(gripper=12.5))["gripper.pos"] == 12.5
    assert fake.wait_for(lambda f: len(f.snapshot().gripper) >= 3)
    assert [g.angle for g in fake.snapshot().gripper] == [0, 70_000, 12_500]
    assert {(g.effort, g.code) for g in fake.snapshot().gripper} == {(1_000, 0x01)}  # default 1 N·m, enabled


def test_arm_follows_the_commands(make_fake, make_robot):
    make_fake()
    robot = make_robot(max_relative_target=5.0)
    robot.connect()
    target = action(joint_1=30.0, joint_3=-20.0, gripper=50.0)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        try:
            robot.send_action(target)
            obs = robot.get_observation()
        except PiperNoFeedbackError:
            # The adapter forgives feedback gaps up to feedback_grace_s, but on a busy 2-core
            # machine the fake arm's thread can stall longer. Refusing to move then is the
            # adapter's job (tested below); here only the convergence is asserted.
            time.sleep(1 / 30)
            continue
        if obs == pytest.approx(target, abs=1e-6):
            break
        time.sleep(1 / 30)
    assert robot.get_observation() == pytest.approx(target, abs=1e-6)


def test_bad_actions_are_rejected_and_nothing_is_sent(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot()
    robot.connect()
    incomplete = action()
    del incomplete["joint_4.pos"]
    with pytest.raises(ValueError, match=r"joint_4\.pos"):
        robot.send_action(incomplete)
    with pytest.raises(ValueError, match="not finite"):
        robot.send_action(action(joint_2=math.nan))
    time.sleep(0.05)
    assert no_motion_commands(fake)


def test_not_connected_raises(make_robot):
    robot = make_robot()
    with pytest.raises(DeviceNotConnectedError):
        robot.get_observation()
    with pytest.raises(DeviceNotConnectedError):
        robot.send_action(action())


# ---------------------------------------------------------------- no feedback / never enables


def test_no_joint_feedback_refuses_to_move(make_fake, make_robot, caplog):
    fake = make_fake(send_joint_feedback=False)  # drivers answer (so it enables), joints never report
    robot = make_robot(feedback_timeout_s=0.2)
    with caplog.at_level(logging.WARNING):
        robot.connect()
    assert robot.is_connected and fake.enabled
    assert "no joint or gripper feedback" in caplog.text
    with pytest.raises(PiperNoFeedbackError, match="refusing"):
        robot.send_action(action(joint_1=20.0))
    with pytest.raises(PiperNoFeedbackError):
        robot.get_observation()
    time.sleep(0.05)
    assert no_motion_commands(fake)


def test_feedback_lost_mid_run_stops_commands(make_fake, make_robot):
    fake = make_fake()
    robot = make_robot()
    robot.connect()
    robot.send_action(action())
    fake.pause_feedback()
    # piper_sdk's rate counter drops to 0 within a couple of its 0.1 s windows.
    deadline = time.monotonic() + 2.0
    while True:
        try:
            robot.get_observation()
        except PiperNoFeedbackError:
            break
        assert time.monotonic() < deadline, "lost feedback was not noticed"
        time.sleep(0.02)
    sent_before = len(fake.snapshot().joint_frames)
    with pytest.raises(PiperNoFeedbackError):
        robot.send_action(action(joint_1=20.0))
    time.sleep(0.05)
    assert len(fake.snapshot().joint_frames) == sent_before
    fake.pause_feedback(False)  # the cable is back: so is the robot
    assert fake.wait_for(lambda f: has_feedback(robot), timeout=2.0)


class _RateStubArm:
    """Just the two feedback getters of ``C_PiperInterface_V2``, with rates set by the test."""

    def __init__(self) -> None:
        self.joint_hz = 200.0
        self.gripper_hz = 200.0

    def GetArmJointMsgs(self):  # noqa: N802 (piper_sdk's name)
        state = {f"joint_{i}": mdeg for i, mdeg in enumerate(START_MDEG, start=1)}
        return SimpleNamespace(Hz=self.joint_hz, joint_state=SimpleNamespace(**state))

    def GetArmGripperMsgs(self):  # noqa: N802
        return SimpleNamespace(Hz=self.gripper_hz, gripper_state=SimpleNamespace(grippers_angle=START_GRIPPER_UM))


def test_feedback_grace_tolerates_a_short_gap_and_not_a_long_one(tmp_path):
    # Deterministic: a stub arm and an injected clock instead of the SDK's 0.1 s rate windows.
    robot = Piper(PiperConfig(calibration_dir=tmp_path, feedback_grace_s=0.3))
    arm, now = _RateStubArm(), [100.0]
    robot._arm, robot._connected, robot._clock = arm, True, lambda: now[0]
    assert robot.get_observation()["joint_1.pos"] == START_DEG["joint_1"]  # frames seen at t=100.0
    arm.joint_hz = 0.0  # one empty SDK window: a stalled process, or the cable came loose
    now[0] = 100.25
    assert robot.get_observation()["joint_1.pos"] == START_DEG["joint_1"]  # within the grace
    now[0] = 100.35
    with pytest.raises(PiperNoFeedbackError, match="no joint feedback"):
        robot.get_observation()
    with pytest.raises(PiperNoFeedbackError):
        robot.send_action(action(joint_1=20.0))  # raised before anything reaches the (stub) arm
    arm.joint_hz = 200.0  # frames again: usable at once
    assert robot.get_observation()["joint_1.pos"] == START_DEG["joint_1"]
    # A stream never seen gets no grace; and a reconnect starts from scratch.
    robot._feedback_seen.clear()
    arm.gripper_hz = 0.0
    with pytest.raises(PiperNoFeedbackError, match="no gripper feedback"):
        robot.get_observation()


def test_zero_grace_trusts_the_sdk_window_alone(tmp_path):
    robot = Piper(PiperConfig(calibration_dir=tmp_path, feedback_grace_s=0.0))
    arm, now = _RateStubArm(), [5.0]
    robot._arm, robot._connected, robot._clock = arm, True, lambda: now[0]
    robot.get_observation()
    arm.joint_hz = 0.0
    now[0] = 5.001
    with pytest.raises(PiperNoFeedbackError):
        robot.get_observation()


def test_silent_arm_connect_fails_within_timeout(make_fake, make_robot, channel):
    make_fake(send_feedback=False)
    robot = make_robot(enable_timeout_s=0.5)
    start = time.monotonic()
    with pytest.raises(PiperConnectionError, match="no feedback"):
        robot.connect()
    assert time.monotonic() - start < 0.5 + 1.0
    assert not robot.is_connected
    assert not sdk_port_connected(channel)
    robot.disconnect()
    robot.disconnect()


def test_arm_never_enables(make_fake, make_robot, channel):
    fake = make_fake(never_enable=True)
    robot = make_robot(enable_timeout_s=0.5)
    start = time.monotonic()
    with pytest.raises(PiperEnableTimeoutError, match="did not report enabled"):
        robot.connect()
    assert time.monotonic() - start < 0.5 + 1.0
    assert not robot.is_connected
    assert not sdk_port_connected(channel)
    robot.disconnect()  # safe after a failed connect, and idempotent
    robot.disconnect()
    snap = fake.snapshot()
    assert len(snap.enables) >= 2 and set(snap.enables) == {(7, ENABLE_FLAG)}  # retried, never disabled
    assert no_motion_commands(fake)
    with pytest.raises(DeviceNotConnectedError):
        robot.send_action(action())


# ---------------------------------------------------------------- disconnect


def test_disconnect_leaves_arm_enabled_by_default(make_fake, make_robot, channel):
    fake = make_fake()
    robot = make_robot()
    robot.connect()
    robot.send_action(action(joint_1=12.0))
    robot.disconnect()
    robot.disconnect()  # idempotent
    assert not robot.is_connected and not sdk_port_connected(channel)
    time.sleep(0.05)
    snap = fake.snapshot()
    assert (7, DISABLE_FLAG) not in snap.enables and fake.enabled
    assert all(g.code == 0x01 for g in snap.gripper)
    with pytest.raises(DeviceNotConnectedError):
        robot.send_action(action())


def test_disconnect_disables_when_asked(make_fake, make_robot, channel):
    fake = make_fake()
    robot = make_robot(disable_on_disconnect=True)
    robot.connect()
    robot.send_action(action())
    robot.disconnect()
    assert not sdk_port_connected(channel)
    snap = fake.snapshot()
    assert (7, DISABLE_FLAG) in snap.enables and not fake.enabled
    assert snap.gripper[-1].code == 0x00  # gripper released too
    robot.disconnect()


def test_reconnect_on_the_same_port(make_fake, make_robot):
    make_fake()
    robot = make_robot()
    robot.connect()
    robot.disconnect()
    robot.connect()  # piper_sdk hands back the same interface object: it must come back to life
    assert robot.get_observation()["joint_1.pos"] == pytest.approx(10.0)
    assert robot.send_action(action(joint_1=11.0))["joint_1.pos"] == 11.0


def test_one_port_one_robot(make_fake, make_robot):
    make_fake()
    first, second = make_robot(), make_robot()
    first.connect()
    with pytest.raises(DeviceAlreadyConnectedError):
        first.connect()
    with pytest.raises(DeviceAlreadyConnectedError, match="another Piper"):
        second.connect()
    second.disconnect()  # must not touch the first robot's port
    assert first.get_observation()["joint_2.pos"] == pytest.approx(45.5)


def test_missing_piper_sdk_says_how_to_install(make_robot, monkeypatch):
    monkeypatch.setitem(sys.modules, "piper_sdk", None)  # makes `import piper_sdk` fail
    robot = make_robot()
    with pytest.raises(ImportError, match=r"pip install 'lerobot-armory\[piper\]'"):
        robot.connect()
    assert not robot.is_connected


@pytest.mark.slow
@pytest.mark.subprocess
def test_config_module_needs_neither_piper_sdk_nor_python_can():
    code = (
        "import sys; sys.modules['piper_sdk'] = None; sys.modules['can'] = None\n"
        "from lerobot_armory.robot.piper import PiperConfig, Piper\n"
        "assert PiperConfig().type == 'piper'\n"
    )
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


# ---------------------------------------------------------------- clamping property


finite = st.floats(min_value=-1000, max_value=1000, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    goal=st.fixed_dictionaries({name: finite for name in MOTOR_NAMES}),
    present=st.fixed_dictionaries({name: finite for name in MOTOR_NAMES}),
    cap=st.one_of(st.none(), st.floats(min_value=0.01, max_value=50)),
)
def test_clamp_targets_respects_limits_and_cap(goal, present, cap):
    safe = clamp_targets(goal, present, dict.fromkeys(MOTOR_NAMES, cap))
    for name in MOTOR_NAMES:
        low, high = GRIPPER_RANGE_MM if name == "gripper" else JOINT_LIMITS_DEG[name]
        if cap is None:
            assert low <= safe[name] <= high
            assert safe[name] == min(max(goal[name], low), high)
            continue
        assert abs(safe[name] - present[name]) <= cap + 1e-9
        if low <= present[name] <= high:  # from inside the range, never leave it
            assert low <= safe[name] <= high
        if low <= goal[name] <= high and abs(goal[name] - present[name]) <= cap:
            assert safe[name] == pytest.approx(goal[name], abs=1e-9)  # float rounding at the edge


# ---------------------------------------------------------------- configuration


def test_config_defaults():
    cfg = PiperConfig()
    assert cfg.type == "piper"
    assert (cfg.can_port, cfg.can_bustype, cfg.cameras) == ("can0", "socketcan", {})
    assert cfg.max_relative_target is None and cfg.disable_on_disconnect is False
    assert cfg.enable_timeout_s == 5.0 and 1 <= cfg.speed_ratio <= 100
    assert PiperConfig(max_relative_target=5).max_relative_target == 5.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"can_port": ""}, "robot.can_port"),
        ({"can_bustype": " "}, "robot.can_bustype"),
        ({"speed_ratio": 0}, "robot.speed_ratio"),
        ({"speed_ratio": 101}, "robot.speed_ratio"),
        ({"speed_ratio": 50.5}, "robot.speed_ratio"),
        ({"gripper_effort": -0.1}, "robot.gripper_effort"),
        ({"gripper_effort": 5.5}, "robot.gripper_effort"),
        ({"gripper_effort": math.nan}, "robot.gripper_effort"),
        ({"max_relative_target": 0.0}, "robot.max_relative_target"),
        ({"max_relative_target": -1.0}, "robot.max_relative_target"),
        ({"max_relative_target": math.inf}, "robot.max_relative_target"),
        ({"max_relative_target": {"elbow": 5.0}}, "robot.max_relative_target"),
        ({"max_relative_target": {"joint_1": -5.0}}, "robot.max_relative_target.joint_1"),
        ({"enable_timeout_s": 0}, "robot.enable_timeout_s"),
        ({"feedback_timeout_s": -1.0}, "robot.feedback_timeout_s"),
        ({"feedback_grace_s": -0.1}, "robot.feedback_grace_s"),
        ({"feedback_grace_s": 5.0}, "robot.feedback_grace_s"),
        ({"feedback_grace_s": math.inf}, "robot.feedback_grace_s"),
        ({"disable_on_disconnect": "yes"}, "robot.disable_on_disconnect"),
    ],
)
def test_config_validation(kwargs, field):
    with pytest.raises(ConfigError) as info:
        PiperConfig(**kwargs)
    assert info.value.field == field
    assert isinstance(info.value, ValueError)


@dataclass
class _Cli:
    robot: RobotConfig


def test_command_line_parses_like_the_docs_say():
    cfg = draccus.parse(
        _Cli,
        args=[
            "--robot.type=piper",
            "--robot.can_port=can1",
            '--robot.cameras={"wrist": {"type": "opencv", "index_or_path": 0, "width": 640, "height": 480, "fps": 30}}',
            "--robot.max_relative_target=5",
            "--robot.speed_ratio=80",
            "--robot.disable_on_disconnect=true",
        ],
    ).robot
    assert isinstance(cfg, PiperConfig)
    assert (cfg.can_port, cfg.max_relative_target, cfg.speed_ratio, cfg.disable_on_disconnect) == ("can1", 5.0, 80, True)
    assert cfg.cameras["wrist"].type == "opencv" and (cfg.cameras["wrist"].height, cfg.cameras["wrist"].width) == (480, 640)


def test_make_robot_from_config_builds_a_piper(tmp_path):
    robot = make_robot_from_config(PiperConfig(can_port="can7", calibration_dir=tmp_path))
    assert isinstance(robot, Piper) and robot.name == "piper"
    assert not robot.is_connected
    robot.disconnect()  # harmless when never connected

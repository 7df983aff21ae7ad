"""Every LeRobot robot from ``lerobot-armory-client``, without hardware.

- every robot type LeRobot ships is found, parses through the client's config and builds
  (or, where its SDK is not installed, fails with one line naming the package);
- non-``.pos`` features (LeKiwi's base velocities, Reachy 2's mobile base, bimanual prefixes)
  map to and from the policy's vectors in the robot's declared order;
- an ``so101_follower`` whose Feetech bus and OpenCV camera are fakes runs the whole client
  against a real server serving a 6-dimensional ACT: the goal positions written to the motors
  are the chunks' actions, index after index;
- a missing port, silent motors, a missing SDK are one line and exit 1; a policy whose action
  size does not fit is refused right after registering, and its session is given back.
"""

from __future__ import annotations

import dataclasses
import errno
import importlib.util
import json
import subprocess
import sys
import time
import typing
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from lerobot.robots.config import RobotConfig
from lerobot.robots.utils import make_robot_from_config
from lerobot.utils.errors import DeviceNotConnectedError

from lerobot_armory.cli_util import parse_or_exit
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.robot.actions import ActionBuffer
from lerobot_armory.robot.cli import ClientConfig, main
from lerobot_armory.robot.connection import Connection
from lerobot_armory.robot.features import IMAGES, STATE, FeatureMap
from lerobot_armory.robot.hardware import explain_robot_error
from lerobot_armory.robot.robot_types import lerobot_robot_types, register_robot_types, robot_types
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.wire import FeatureSpec
from lerobot_armory.engine.protocol import UnguidedEngine

register_robot_types()  # at import: the parametrised test below needs the types at collection
LEROBOT_TYPES = lerobot_robot_types()
#: The robot types lerobot 0.6.1 ships; a newer LeRobot may add more (found by themselves).
LEROBOT_061 = {
    "so100_follower", "so101_follower", "bi_so_follower", "koch_follower", "omx_follower", "lekiwi", "lekiwi_client",
    "reachy2", "hope_jr_arm", "hope_jr_hand", "openarm_follower", "bi_openarm_follower", "rebot_b601_follower",
    "bi_rebot_b601_follower", "earthrover_mini_plus", "unitree_g1",
}  # fmt: skip
SO101_MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
SO101_KEYS = tuple(f"{m}.pos" for m in SO101_MOTORS)
HAVE_FEETECH = importlib.util.find_spec("scservo_sdk") is not None and importlib.util.find_spec("serial") is not None
REPO = Path(__file__).resolve().parents[2]
CAMERA = '--robot.cameras={"front": {"type": "opencv", "index_or_path": 0, "width": 32, "height": 32, "fps": 30}}'


# ---- discovery -------------------------------------------------------------------------------


def test_every_lerobot_robot_type_is_found_with_ours():
    assert set(LEROBOT_TYPES) >= LEROBOT_061
    assert {"armory_sim", "piper"} <= set(robot_types())
    from lerobot.cameras import CameraConfig

    assert {"opencv", "intelrealsense"} <= set(CameraConfig.get_known_choices())
    realsense = (
        '{"d": {"type": "intelrealsense", "serial_number_or_name": "0123", "width": 640, "height": 480, "fps": 30}}'
    )
    cfg = parse_or_exit(
        ClientConfig, ["--robot.type=so101_follower", "--robot.port=/dev/ttyX", f"--robot.cameras={realsense}"], "t"
    )
    assert cfg.robot.cameras["d"].type == "intelrealsense" and cfg.robot.cameras["d"].width == 640


def test_a_robot_package_that_fails_to_import_is_skipped_not_fatal(tmp_path, monkeypatch, caplog):
    from lerobot_armory.robot import robot_types as rt

    root = tmp_path / "armory_fake_robots"
    for sub, body in {
        "good": "from dataclasses import dataclass\nfrom lerobot.robots.config import RobotConfig\n\n"
        '@RobotConfig.register_subclass("armory_test_discovered")\n@dataclass\nclass GoodConfig(RobotConfig):\n    pass\n',
        "broken": "raise RuntimeError('this robot module is broken')\n",
        "no_sdk": "import armory_no_such_sdk\n",
    }.items():
        (root / sub).mkdir(parents=True)
        (root / sub / "__init__.py").write_text("")
        (root / sub / f"config_{sub}.py").write_text(body)
    (root / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    with caplog.at_level("DEBUG", logger=rt.__name__):
        rt._import_config_modules("armory_fake_robots")
    assert "armory_test_discovered" in rt.robot_types()
    assert "RuntimeError" in rt.SKIPPED["armory_fake_robots.broken.config_broken"]
    assert "armory_no_such_sdk" in rt.SKIPPED["armory_fake_robots.no_sdk.config_no_sdk"]
    levels = {r.getMessage().split()[1]: r.levelname for r in caplog.records}
    assert levels == {
        "armory_fake_robots.broken.config_broken": "WARNING",
        "armory_fake_robots.no_sdk.config_no_sdk": "DEBUG",
    }


def test_help_lists_the_robot_types(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for name in [*LEROBOT_TYPES, "armory_sim", "piper"]:
        assert name in out


def _placeholder(field: str) -> str:
    """A value for a required config field that parses (nothing is opened: no connect)."""
    return {"side": "right", "remote_ip": "127.0.0.1"}.get(field.rpartition(".")[2], "/dev/ttyNOPE")


def _required_args(cls: type, prefix: str = "--robot.") -> list[str]:
    """``--robot.<field>=...`` for every field without a default (nested arm configs included)."""
    hints = typing.get_type_hints(cls)
    args = []
    for f in dataclasses.fields(cls):
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            if dataclasses.is_dataclass(hints[f.name]):
                args += _required_args(hints[f.name], f"{prefix}{f.name}.")
            else:
                args.append(f"{prefix}{f.name}={_placeholder(f.name)}")
    return args


@pytest.mark.parametrize("robot_type", LEROBOT_TYPES)
def test_lerobot_robot_parses_and_builds(robot_type, tmp_path):
    cls = RobotConfig.get_choice_class(robot_type)
    args = [f"--robot.type={robot_type}", f"--robot.calibration_dir={tmp_path}", *_required_args(cls)]
    cfg = parse_or_exit(ClientConfig, args, "lerobot-armory-client")
    assert isinstance(cfg.robot, cls)
    try:
        robot = make_robot_from_config(cfg.robot)
    except Exception as exc:
        # The one acceptable failure: an optional SDK that is not installed here, said in one line.
        line = explain_robot_error(exc, cfg.robot, robot_type)
        assert "\n" not in line and line.startswith(f"robot {robot_type}") and "not installed" in line, line
        pytest.skip(line)
    assert not robot.is_connected
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    assert fmap.state_keys == tuple(k for k, v in robot.observation_features.items() if v is float)
    assert fmap.action_keys == tuple(k for k, v in robot.action_features.items() if v is float)


# ---- features that are not "<motor>.pos" -------------------------------------------------------


class FakeFeetechBus:
    """Stands in for LeRobot's ``FeetechMotorsBus``: no serial port, servos that reach each goal.

    Records every ``sync_write`` (time, goal dict) and answers ``sync_read`` with the present
    positions (the last goals written, from a fixed start pose).
    """

    instances: typing.ClassVar[list[FakeFeetechBus]] = []
    is_calibrated = True

    def __init__(self, port: str, motors: dict, calibration: dict | None = None, **_: object) -> None:
        self.port, self.motors, self.calibration = port, motors, calibration
        self.is_connected = False
        self.positions = {m: 10.0 * k - 20.0 for k, m in enumerate(motors)}
        self.writes: list[tuple[float, str, dict[str, float]]] = []
        self.reads = 0
        FakeFeetechBus.instances.append(self)

    def connect(self, handshake: bool = True) -> None:
        self.is_connected = True

    def disconnect(self, disable_torque: bool = True) -> None:
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self.port} is not connected")
        self.is_connected = False

    @contextmanager
    def torque_disabled(self, motors=None):
        yield

    def configure_motors(self, *args: object, **kwargs: object) -> None:
        pass

    def write(self, data_name: str, motor: str, value: float, **kwargs: object) -> None:
        pass

    def sync_read(self, data_name: str, motors=None, **kwargs: object) -> dict[str, float]:
        assert data_name == "Present_Position"
        self.reads += 1
        return dict(self.positions)

    def sync_write(self, data_name: str, values: dict[str, float], **kwargs: object) -> None:
        self.writes.append((time.monotonic(), data_name, dict(values)))
        if data_name == "Goal_Position":
            self.positions.update(values)


class FakeCamera:
    """Stands in for LeRobot's ``OpenCVCamera``: frames of the configured size, no device."""

    def __init__(self, config) -> None:
        self.config, self.width, self.height = config, config.width, config.height
        self.is_connected = False
        self.frames = 0

    def connect(self, warmup: bool = True) -> None:
        self.is_connected = True

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        self.frames += 1
        return np.full((self.height, self.width, 3), self.frames % 256, np.uint8)

    read = read_latest

    def disconnect(self) -> None:
        self.is_connected = False


@pytest.fixture
def fake_hardware(monkeypatch):
    """Every Feetech bus and OpenCV camera LeRobot builds in this test is a fake."""
    import lerobot.cameras.opencv

    FakeFeetechBus.instances.clear()
    monkeypatch.setattr("lerobot.robots.so_follower.so_follower.FeetechMotorsBus", FakeFeetechBus)
    monkeypatch.setattr("lerobot.robots.lekiwi.lekiwi.FeetechMotorsBus", FakeFeetechBus)
    monkeypatch.setattr(lerobot.cameras.opencv, "OpenCVCamera", FakeCamera)
    return FakeFeetechBus.instances


def test_lekiwi_base_velocities_map_in_declared_order(fake_hardware, tmp_path):
    from lerobot.robots.lekiwi import LeKiwiConfig

    robot = make_robot_from_config(LeKiwiConfig(calibration_dir=tmp_path))  # LeRobot's LeKiwi, fake bus
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    assert fmap.state_keys[-3:] == ("x.vel", "y.vel", "theta.vel") and len(fmap.state_keys) == 9
    assert fmap.action_keys == fmap.state_keys == tuple(robot.action_features)
    assert fmap.cameras == {"front": (480, 640, 3), "wrist": (640, 480, 3)}
    raw = {k: float(i) for i, k in enumerate(fmap.state_keys)} | {
        "front": np.zeros((480, 640, 3), np.uint8),
        "wrist": np.zeros((640, 480, 3), np.uint8),
    }
    wire = fmap.to_wire(raw)
    np.testing.assert_array_equal(wire[STATE], np.arange(9, dtype=np.float32))
    assert wire[IMAGES + "wrist"].shape == (640, 480, 3)
    action = fmap.to_action(np.arange(9, dtype=np.float32) / 10)
    assert list(action) == list(robot.action_features) and action["theta.vel"] == pytest.approx(0.8)


def test_reachy2_mobile_base_and_bimanual_prefixes_map_in_declared_order(monkeypatch, tmp_path):
    from lerobot.robots.bi_openarm_follower import BiOpenArmFollowerConfig
    from lerobot.robots.openarm_follower.config_openarm_follower import OpenArmFollowerConfigBase
    from lerobot.robots.reachy2 import Reachy2RobotConfig

    # Reachy 2 is built by LeRobot's own class; only its SDK check is skipped (nothing connects).
    monkeypatch.setattr("lerobot.robots.reachy2.robot_reachy2.require_package", lambda *a, **k: None)
    reachy = make_robot_from_config(Reachy2RobotConfig(calibration_dir=tmp_path))
    fmap = FeatureMap.for_robot(reachy.observation_features, reachy.action_features)
    assert fmap.action_keys[-3:] == ("mobile_base.vx", "mobile_base.vy", "mobile_base.vtheta")
    assert fmap.action_keys == fmap.state_keys == tuple(reachy.action_features)
    assert list(fmap.to_action(np.zeros(len(fmap.action_keys)))) == list(reachy.action_features)

    arm = dict(port="can0")
    bi = make_robot_from_config(
        BiOpenArmFollowerConfig(
            left_arm_config=OpenArmFollowerConfigBase(**arm), right_arm_config=OpenArmFollowerConfigBase(**arm),
            calibration_dir=tmp_path,
        )
    )  # fmt: skip
    fmap = FeatureMap.for_robot(bi.observation_features, bi.action_features)
    n = len(fmap.action_keys) // 2
    assert all(k.startswith("left_") for k in fmap.action_keys[:n]) and all(
        k.startswith("right_") for k in fmap.action_keys[n:]
    )
    assert fmap.action_keys == tuple(bi.action_features)
    vector = np.arange(2 * n, dtype=np.float32)
    assert [v for v in fmap.to_action(vector).values()] == vector.tolist()


def test_feature_map_refuses_what_it_cannot_send():
    with pytest.raises(ValueError, match="wrist"):
        FeatureMap.for_robot({"a.pos": float, "wrist": (None, None, 3)}, {"a.pos": float})
    depth = FeatureMap.for_robot({"a.pos": float, "cam_depth": (4, 4, 1)}, {"a.pos": float})
    with pytest.raises(ValueError, match="uint16"):  # never wrapped modulo 256
        depth.to_wire({"a.pos": 0.0, "cam_depth": np.full((4, 4, 1), 1000, np.uint16)})
    assert depth.action_mismatch(1, "x") is None
    assert depth.action_mismatch(2, "x") == "the policy's actions have 2 dims, robot x takes 1 (a.pos)"


# ---- so101 against a real server ---------------------------------------------------------------


@pytest.fixture(scope="module")
def so101_engine(tmp_path_factory):
    """A tiny random ACT whose state and actions are so101's 6 motors, one 32² camera."""
    import torch

    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions

    out = tmp_path_factory.mktemp("policy") / "so101-act"
    make_demo_policy(
        DemoPolicyConfig(
            output=str(out),
            chunk_size=10,
            state_dim=6,
            cameras="front",
            image_size=32,
            dim_model=32,
            n_encoder_layers=1,
        )
    )
    torch.set_num_threads(1)
    return PolicyEngine(PolicyOptions(str(out), "cpu"))


def so101_args(server: ArmoryServer, tmp_path: Path, *extra: str) -> list[str]:
    return [
        "--robot.type=so101_follower", "--robot.port=/dev/ttyFAKE", f"--robot.calibration_dir={tmp_path}", CAMERA,
        f"--server_address={server.address}", "--fps=20", "--h_min=2", "--h_max=8", "--give_up_s=10", *extra,
    ]  # fmt: skip


@pytest.mark.slow
def test_so101_runs_the_client_loop_and_its_motors_get_the_chunks_in_order(
    so101_engine, fake_hardware, monkeypatch, tmp_path, capsys
):
    engine = so101_engine
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    server = ArmoryServer(
        engine, info, LatencyProfile("t", (15.0, 20.0, 25.0)), EarliestDeadlineConfig(), 3, port=0
    ).start()
    chunks: list[tuple[int, int, np.ndarray, float]] = []
    observations: list[dict[str, np.ndarray]] = []
    add, send = ActionBuffer.add, Connection.send_observation

    def spy_add(self, chunk_id, i_start, actions, arrival):
        chunks.append((chunk_id, i_start, np.array(actions), arrival))
        return add(self, chunk_id, i_start, actions, arrival)

    def spy_send(self, index, arrays, *args, **kwargs):
        observations.append({k: np.array(v) for k, v in arrays.items()})
        return send(self, index, arrays, *args, **kwargs)

    monkeypatch.setattr(ActionBuffer, "add", spy_add)
    monkeypatch.setattr(Connection, "send_observation", spy_send)
    stats_path = tmp_path / "stats.json"
    try:
        main(so101_args(server, tmp_path, "--duration_s=3", f"--stats_path={stats_path}"))
    finally:
        server.stop(grace_s=0.5)
    stats = json.loads(stats_path.read_text())
    (bus,) = fake_hardware
    assert bus.port == "/dev/ttyFAKE" and not bus.is_connected  # disconnected at the end
    assert stats["robot_id"].startswith("so101_follower-")  # the type as typed, not its alias so100
    assert stats["executed_steps"] > 10 and stats["chunks_received"] > 0
    assert stats["executed_steps"] + stats["starved_steps"] == stats["ticks"]

    # Observations: so101's 6 positions in motor order, and the camera.
    assert len(observations) == stats["ticks"]
    start = np.array([10.0 * k - 20.0 for k in range(6)], np.float32)
    np.testing.assert_array_equal(observations[0][STATE], start)
    assert observations[0][IMAGES + "front"].shape == (32, 32, 3)

    # Actions: the k-th goal written is index k's action of the newest arrived chunk covering k.
    goals = [(t, values) for t, name, values in bus.writes if name == "Goal_Position"]
    assert len(goals) == stats["executed_steps"]
    for k, (t, values) in enumerate(goals):
        assert tuple(values) == SO101_MOTORS
        covering = [c for c in chunks if c[3] <= t and c[1] <= k < c[1] + 8]
        assert covering, f"index {k} written with no covering chunk"
        chunk_id, i_start, actions, _ = max(covering, key=lambda c: (c[1], c[0]))
        np.testing.assert_allclose(list(values.values()), actions[k - i_start], rtol=1e-6)
    # ... and the state sent next is what the bus then reads back: the goal, in motor order.
    assert any(np.allclose(o[STATE], list(goals[0][1].values()), rtol=1e-6) for o in observations)
    assert "executed" in capsys.readouterr().out


class SevenDimEngine(UnguidedEngine):
    """A policy for so101's observations whose actions have 7 dims."""

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        return np.zeros((len(observations), 10, 7), np.float32)


def test_a_policy_whose_actions_do_not_fit_is_refused_at_registration(fake_hardware, tmp_path, capsys):
    features = [FeatureSpec(STATE, "float32", (6,)), FeatureSpec(IMAGES + "front", "uint8", (32, 32, 3))]
    info = PolicyInfo("seven", features, [f"a{i}" for i in range(7)], 10)
    server = ArmoryServer(
        SevenDimEngine(), info, LatencyProfile("t", (5.0, 6.0)), EarliestDeadlineConfig(), 2, port=0
    ).start()
    try:
        with pytest.raises(SystemExit) as exit_info:
            main(so101_args(server, tmp_path, "--duration_s=2"))
        deadline = time.monotonic() + 3.0
        while server.fleet.sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not server.fleet.sessions, "the refused registration still holds a fleet slot"
    finally:
        server.stop(grace_s=0.5)
    assert exit_info.value.code == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("lerobot-armory-client:")]
    assert lines == [
        "lerobot-armory-client: the policy's actions have 7 dims, robot so101_follower takes 6 ("
        + ", ".join(SO101_KEYS)
        + ")"
    ]
    (bus,) = fake_hardware
    assert not [w for w in bus.writes if w[1] == "Goal_Position"] and not bus.is_connected


# ---- missing hardware: one line, exit 1 --------------------------------------------------------


def run_cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "lerobot_armory.robot.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_missing_serial_port_is_one_line_and_exit_1(tmp_path):
    # A fresh process: the OpenCV camera config must parse with nothing imported but the client.
    done = run_cli(
        "--robot.type=so101_follower", "--robot.port=/dev/ttyNOPE", f"--robot.calibration_dir={tmp_path}", CAMERA,
        "--server_address=127.0.0.1:1",
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    line = done.stderr.strip()
    assert line.startswith("lerobot-armory-client: robot so101_follower on /dev/ttyNOPE: "), line
    if HAVE_FEETECH:
        assert "/dev/ttyNOPE does not exist" in line
    else:  # LeRobot's feetech extra is not installed here: that is the line, naming the extra
        assert "lerobot[feetech]" in line


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.skipif(not HAVE_FEETECH, reason="needs LeRobot's feetech extra (feetech-servo-sdk, pyserial)")
def test_motors_that_do_not_answer_are_one_line_and_exit_1(tmp_path):
    import os
    import tty

    controller, port = os.openpty()  # a serial port on which nothing answers
    tty.setraw(port)
    try:
        done = run_cli(
            "--robot.type=so101_follower", f"--robot.port={os.ttyname(port)}", f"--robot.calibration_dir={tmp_path}"
        )
    finally:
        os.close(port)
        os.close(controller)
    assert done.returncode == 1, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "motor(s) 1, 2, 3, 4, 5, 6 do not answer" in done.stderr


def _raised(outer: BaseException, cause: BaseException) -> BaseException:
    try:
        try:
            raise cause
        except BaseException as inner:
            raise outer from inner
    except BaseException as exc:
        return exc


@pytest.mark.parametrize(
    ("exc", "expected"),
    [
        # LeRobot's MotorsBus._connect wraps pyserial's SerialException (an OSError with errno).
        (
            _raised(
                ConnectionError("\nCould not connect on port '/dev/ttyACM0'. Make sure you are using the correct port.\n"),
                OSError(errno.ENOENT, "could not open port /dev/ttyACM0: [Errno 2] No such file or directory"),
            ),
            "robot so101_follower on /dev/ttyACM0: /dev/ttyACM0 does not exist",
        ),
        (
            _raised(
                ConnectionError("\nCould not connect on port '/dev/ttyACM0'. Make sure you are using the correct port.\n"),
                OSError(errno.EACCES, "could not open port /dev/ttyACM0: [Errno 13] Permission denied"),
            ),
            "robot so101_follower on /dev/ttyACM0: permission denied on /dev/ttyACM0 (add your user to the 'dialout' group",
        ),
        (
            RuntimeError(
                "FeetechMotorsBus motor check failed on port '/dev/ttyACM0':\n\nMissing motor IDs:\n"
                "  - 5 (expected model: 777)\n  - 6 (expected model: 777)\n"
            ),
            "robot so101_follower on /dev/ttyACM0: motor(s) 5, 6 do not answer",
        ),
        (
            ConnectionError("Failed to sync read 'Present_Position' on ids=[1, 2] after 3 tries. [TxRxResult] There is no status packet!"),
            "robot so101_follower on /dev/ttyACM0: the motors do not answer (Failed to sync read",
        ),
        (
            ImportError("'feetech-servo-sdk' is required but not installed. Install it with: pip install 'lerobot[feetech]'"),
            "robot so101_follower on /dev/ttyACM0: 'feetech-servo-sdk' is required but not installed",
        ),
        (
            _raised(ValueError("Error creating robot with config X(port='/dev/ttyACM0', ...): No module named 'zmq'"),
                    ModuleNotFoundError("No module named 'zmq'", name="zmq")),
            "robot so101_follower on /dev/ttyACM0: the Python package 'zmq' it needs is not installed",
        ),
        (DeviceNotConnectedError("SOFollower is not connected."), "robot so101_follower on /dev/ttyACM0: not connected ("),
        (EOFError("EOF when reading a line"), "robot so101_follower on /dev/ttyACM0: needs a calibration"),
    ],
)  # fmt: skip
def test_robot_errors_become_one_line_naming_robot_and_port(exc, expected):
    from lerobot.robots.so_follower import SO101FollowerConfig

    line = explain_robot_error(exc, SO101FollowerConfig(port="/dev/ttyACM0"), "so101_follower")
    assert "\n" not in line and line.startswith(expected), line


def test_bimanual_and_can_robots_name_their_ports():
    from lerobot.robots.bi_openarm_follower import BiOpenArmFollowerConfig
    from lerobot.robots.openarm_follower.config_openarm_follower import OpenArmFollowerConfigBase

    from lerobot_armory.robot.piper import PiperConfig, PiperConnectionError

    bi = BiOpenArmFollowerConfig(
        left_arm_config=OpenArmFollowerConfigBase(port="can0"), right_arm_config=OpenArmFollowerConfigBase(port="can1")
    )
    assert (
        explain_robot_error(TimeoutError("no reply"), bi, "bi_openarm_follower")
        == "robot bi_openarm_follower on can0 and can1: no reply"
    )
    piper = PiperConnectionError("cannot open CAN port 'can3' (socketcan): No such device; check ...")
    assert explain_robot_error(piper, PiperConfig(can_port="can3")).startswith(
        "robot piper on can3: cannot open CAN port 'can3'"
    )

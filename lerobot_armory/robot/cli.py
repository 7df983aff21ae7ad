"""``lerobot-armory-client``: run any LeRobot robot against an armory server.

    lerobot-armory-client --robot.type=armory_sim --robot.scene=dynamic \\
        --server_address=127.0.0.1:8080 --fps=30 --h_min=5 --h_max=10 --weight=3 --tier=fast \\
        --duration_s=20 --stats_path=out/robot0.json

    lerobot-armory-client --robot.type=so101_follower --robot.port=/dev/ttyACM0 --robot.id=arm0 \
        --robot.cameras='{"front": {"type": "opencv", "index_or_path": 0, "width": 640, "height": 480, "fps": 30}}' \
        --server_address=gpu-box:8080 --task="pick the cube"

Every robot type is selectable (``--help`` lists them): each one LeRobot ships (found by walking
``lerobot.robots``), third-party ``lerobot_robot_*`` plugins, and the robots shipped here
(``armory_sim``, ``piper``); see :mod:`lerobot_armory.robot.robot_types`. The robot is built with
LeRobot's ``make_robot_from_config``. Exit codes: 0 done; 1 robot unavailable (missing hardware,
port, permission or SDK: one line naming the robot and its port), registration refused (the
server's reason, or a policy whose action size does not fit the robot) or server lost for good
(unreachable or full past ``--give_up_s``: a full server is waited for, like an unreachable one);
2 bad command line; 130 interrupted.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot.robots.config import RobotConfig
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceNotConnectedError

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import spec_problems
from lerobot_armory.robot.client import ArmoryClient, Backoff, RegistrationRefused, RobotIdentity
from lerobot_armory.robot.connection import Registration
from lerobot_armory.robot.features import FeatureMap
from lerobot_armory.robot.hardware import RobotUnavailable, explain_robot_error
from lerobot_armory.robot.robot_types import SKIPPED, register_robot_types

LOG_LEVELS = ("debug", "info", "warning", "error")

log = logging.getLogger("lerobot_armory.client")


@dataclass
class ClientConfig:
    """Options of ``lerobot-armory-client``.

    Attributes:
        robot: ``--robot.type=...`` and its ``--robot.*`` options (any LeRobot robot).
        server_address: ``host:port`` of the armory server.
        robot_id: name in the fleet (default: ``--robot.id``, else type-host-pid).
        task: task text passed to language-conditioned policies.
        fps: control frequency.
        h_min: the server waits for this many executed steps before serving the robot again.
        h_max: executed actions per chunk at most.
        weight: value of this robot's executed time to the operator (Lookahead weight).
        tier: ``fast`` (dynamic task) or ``slow`` (static task), for reporting.
        duration_s: seconds to run (0 = until Ctrl-C).
        stats_path: write the run's stats JSON here at exit.
        jpeg_quality: send camera images as JPEG of this quality (default: raw bytes).
        give_up_s: stop retrying an unreachable or full server after this long (0 = never).
        tls_ca: PEM file of the CA that signed the server's certificate (enables TLS).
        auth_token_file: file whose first line is this robot's token.
        log_level: debug, info, warning, error.
        policy_name: the policy to be served by, where the server serves several
            (``--policies=FILE``); empty: the server's only one.
    """

    robot: RobotConfig
    server_address: str = "127.0.0.1:8080"
    robot_id: str | None = None
    task: str = ""
    fps: float = 30.0
    h_min: int = 1
    h_max: int = 10
    weight: float = 1.0
    tier: str = "slow"
    duration_s: float = 0.0
    stats_path: str | None = None
    jpeg_quality: int | None = None
    give_up_s: float = 0.0
    tls_ca: str | None = None
    auth_token_file: str | None = None
    log_level: str = "info"
    policy_name: str = ""
    backoff: Backoff = field(default_factory=Backoff)

    def validate(self) -> None:
        """Check every option; raises one :class:`ConfigError` naming every problem at once.

        The declared spec goes through the validator the server applies to registrations
        (:func:`~lerobot_armory.robot_spec.spec_problems`), so what passes here is refused there only
        for what the robot cannot know yet: the policy's chunk size (``h_max`` above it) and the
        operator's grant rules.
        """
        problems = spec_problems(default_robot_id(self), self.fps, None, self.h_min, self.h_max, self.weight, self.tier)
        if not self.duration_s >= 0:  # NaN included
            problems.append(f"duration_s: must be >= 0, got {self.duration_s}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            problems.append(f"jpeg_quality: must be in 1..100, got {self.jpeg_quality}")
        if self.log_level.lower() not in LOG_LEVELS:
            problems.append(f"log_level: must be one of {', '.join(LOG_LEVELS)}, got {self.log_level!r}")
        if problems:
            raise ConfigError.listing(problems)


def read_credentials(cfg: ClientConfig) -> tuple[bytes | None, str]:
    """The CA certificate and the token the command line points at."""
    return read_ca(cfg.tls_ca), read_token(cfg.auth_token_file)


def read_ca(path: str | None, field: str = "tls_ca") -> bytes | None:
    """The PEM bytes of ``--tls_ca`` (None: plaintext)."""
    if not path:
        return None
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(field, f"cannot read {path}: {exc}") from None


def read_token(path: str | None, field: str = "auth_token_file") -> str:
    """The token of a token file (its first line that holds one: the last word of it); "" without a file."""
    if not path:
        return ""
    try:
        lines = [ln.split("#", 1)[0].strip() for ln in Path(path).read_text().splitlines()]
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(field, f"cannot read {path}: {exc}") from None
    token = next((ln.split()[-1] for ln in lines if ln), "")
    if not token:
        raise ConfigError(field, f"{path} holds no token")
    return token


def default_robot_id(cfg: ClientConfig, robot_type: str | None = None) -> str:
    kind = robot_type or cfg.robot.type
    return cfg.robot_id or getattr(cfg.robot, "id", None) or f"{kind}-{socket.gethostname()}-{os.getpid()}"


def _configure_logging(level: str) -> None:
    logging.basicConfig(level=level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # LeRobot's import already called basicConfig (its module-level logging.debug does), which
    # makes the call above a no-op: set the level the user asked for on the root logger itself.
    logging.getLogger().setLevel(level.upper())
    for what, reason in SKIPPED.items():
        log.debug("robot/camera module skipped: %s (%s)", what, reason)


def _robot_call[T](robot_cfg: RobotConfig, robot_type: str, fn: Callable[[], T]) -> T:
    """Run one call into the robot; whatever it raises becomes one line naming robot and port."""
    try:
        return fn()
    except RobotUnavailable:
        raise
    except Exception as exc:
        log.debug("robot error", exc_info=True)  # the traceback, for --log_level=debug
        raise RobotUnavailable(explain_robot_error(exc, robot_cfg, robot_type)) from exc


def _disconnect(robot: Robot, failing: bool) -> None:
    """Disconnect whatever state the robot is in, never hiding the error that got us here.

    After a failure (``failing``) the disconnect is expected to fail too (motors that did not
    answer cannot have their torque disabled either): that is logged at debug level only, so the
    user reads one line, the reason.
    """
    try:
        robot.disconnect()
    except DeviceNotConnectedError:
        pass  # connect() failed before the robot counted as connected: nothing to release
    except Exception as exc:
        text = str(exc).strip()
        level = logging.DEBUG if failing else logging.WARNING
        log.log(level, "disconnecting %s failed: %s", robot, text.splitlines()[0] if text else exc)


def typed_robot_type(args: list[str] | None, robot: RobotConfig) -> str:
    """The ``--robot.type`` as typed. LeRobot registers one config class under several names
    (``so100_follower`` and ``so101_follower`` are both ``SOFollowerRobotConfig``) and
    ``robot.type`` answers the first, so messages would name the wrong robot."""
    args = sys.argv[1:] if args is None else args
    choices = RobotConfig.get_known_choices()
    for arg, following in reversed(list(zip(args, [*args[1:], ""], strict=True))):
        name = arg.partition("=")[2] if arg.startswith("--robot.type=") else following if arg == "--robot.type" else ""
        if name:  # the last one given is the one draccus used
            return name if choices.get(name) is type(robot) else robot.type
    return robot.type


def run_client(cfg: ClientConfig, robot_type: str | None = None) -> dict[str, Any]:
    """Build the robot, run the loop, always leave the robot disconnected; returns the stats.

    ``robot_type`` is the robot's name in messages and the default robot id (default: ``cfg.robot.type``).

    Raises:
        RobotUnavailable: the robot could not be built, connected or driven (one-line reason).
        RegistrationRefused: the server refused, or its policy's actions do not fit the robot.
        ConnectionError: the server could not be reached, or stayed full, within ``give_up_s``.
    """
    from lerobot.robots.utils import make_robot_from_config

    cfg.validate()
    _configure_logging(cfg.log_level)
    tls_ca, token = read_credentials(cfg)
    if token and tls_ca is None:
        log.warning("the auth token travels in plaintext (no --tls_ca): anyone on the network path can read and reuse it")
    name = robot_type or cfg.robot.type
    robot = _robot_call(cfg.robot, name, lambda: make_robot_from_config(cfg.robot))
    client: ArmoryClient | None = None

    def on_sigterm(*_: object) -> None:
        if client is None:
            raise KeyboardInterrupt  # still connecting the robot: unwind through the finally below
        client.stop()

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    failing = True
    try:
        _robot_call(cfg.robot, name, robot.connect)
        # Features are read once connected: a camera without a configured size learns it there.
        fmap = _robot_call(
            cfg.robot, name, lambda: FeatureMap.for_robot(robot.observation_features, robot.action_features)
        )

        def check_registration(reg: Registration) -> None:
            refusal = fmap.action_mismatch(reg.action_dim, name)
            if refusal is not None:
                raise RegistrationRefused(refusal)

        client = ArmoryClient(
            cfg.server_address,
            RobotIdentity(default_robot_id(cfg, name), cfg.fps, cfg.h_min, cfg.h_max, cfg.weight, cfg.tier, cfg.task, cfg.policy_name),
            fmap.wire_features(),
            observe=lambda: _robot_call(cfg.robot, name, lambda: fmap.to_wire(robot.get_observation())),
            act=lambda vector: _robot_call(cfg.robot, name, lambda: robot.send_action(fmap.to_action(vector))),
            jpeg_quality=cfg.jpeg_quality,
            backoff=Backoff(cfg.backoff.initial_s, cfg.backoff.max_s, cfg.give_up_s),
            tls_ca=tls_ca,
            token=token,
            check_registration=check_registration,
            # A robot that counts its own episodes (a simulator's resets) tells the server of each.
            episode_of=(lambda: int(robot.episode)) if isinstance(getattr(robot, "episode", None), int) else None,
            finished=(lambda: bool(robot.finished)) if hasattr(robot, "finished") else None,
        )
        try:
            stats = client.run(cfg.duration_s)
        except KeyboardInterrupt:
            log.info("interrupted: holding the robot and disconnecting")
            stats = client.stats()
        failing = False
    finally:
        if client is not None:
            client.close()
        _disconnect(robot, failing)
        signal.signal(signal.SIGTERM, previous)
    if hasattr(robot, "task_stats"):
        task = robot.task_stats()
        stats.update(task)
        minutes = stats["ticks"] / cfg.fps / 60.0
        stats["successes_per_min"] = task.get("successes", 0) / minutes if minutes > 0 else 0.0
    if cfg.stats_path:
        Path(cfg.stats_path).parent.mkdir(parents=True, exist_ok=True)
        Path(cfg.stats_path).write_text(json.dumps(stats, indent=2) + "\n")
    summary = (
        f"{stats['robot_id']}: {stats['ticks']} ticks, executed {stats['executed_steps']}, "
        f"starved {stats['starved_steps']} ({stats['starvation_pct']:.1f}%), chunks {stats['chunks_received']}, "
        f"reconnects {stats['reconnects']}"
    )
    if "successes" in stats:
        summary += f", successes {stats['successes']} ({stats['successes_per_min']:.1f}/min)"
    if stats.get("episodes_done"):  # a robot with episodes (metaworld): the success rate per episode
        summary += f" in {stats['episodes_done']} episodes ({100.0 * stats['success_rate']:.0f}%)"
    print(summary)
    return stats


def _run(cfg: ClientConfig, robot_type: str | None = None) -> None:
    try:
        run_client(cfg, robot_type)
    except (RobotUnavailable, RegistrationRefused, ConnectionError) as exc:
        print(f"lerobot-armory-client: {exc}", file=sys.stderr)
        sys.exit(1)


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    register_robot_types()
    cfg = parse_or_exit(ClientConfig, argv, "lerobot-armory-client")
    robot_type = typed_robot_type(argv, cfg.robot)
    run_or_exit(lambda c: _run(c, robot_type), cfg, "lerobot-armory-client")


if __name__ == "__main__":
    main()

"""``lerobot-armory-client``: run any LeRobot robot against an armory server.

    lerobot-armory-client --robot.type=armory_sim --robot.scene=dynamic \\
        --server_address=127.0.0.1:8080 --fps=30 --h_min=5 --h_max=10 --weight=3 --tier=fast \\
        --duration_s=20 --stats_path=out/robot0.json

The robot is built with LeRobot's ``make_robot_from_config`` (third-party ``lerobot_robot_*``
plugins are registered first, then the robots shipped here: ``armory_sim`` and ``piper``).
Exit codes: 0 done, 1 registration refused or server lost for good (the reason is printed),
2 bad command line, 130 interrupted.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot.robots.config import RobotConfig

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot.client import ArmoryClient, Backoff, RegistrationRefused, RobotIdentity
from lerobot_armory.robot.features import FeatureMap

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
        give_up_s: stop retrying an unreachable server after this long (0 = never).
        tls_ca: PEM file of the CA that signed the server's certificate (enables TLS).
        auth_token_file: file whose first line is this robot's token.
        log_level: debug, info, warning, error.
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
    backoff: Backoff = field(default_factory=Backoff)

    def validate(self) -> None:
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError("fps", f"must be > 0, got {self.fps}")
        if self.h_max < 1:
            raise ConfigError("h_max", f"must be >= 1, got {self.h_max}")
        if not 0 <= self.h_min <= self.h_max:
            raise ConfigError("h_min", f"must be in [0, h_max={self.h_max}], got {self.h_min}")
        if not self.weight > 0:
            raise ConfigError("weight", f"must be > 0, got {self.weight}")
        if self.tier not in ("fast", "slow"):
            raise ConfigError("tier", f"must be fast or slow, got {self.tier!r}")
        if self.duration_s < 0:
            raise ConfigError("duration_s", f"must be >= 0, got {self.duration_s}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ConfigError("jpeg_quality", f"must be in 1..100, got {self.jpeg_quality}")


def register_robot_types() -> None:
    """Make every robot type selectable: third-party plugins, then the ones shipped here."""
    try:
        from lerobot.utils.import_utils import register_third_party_plugins

        register_third_party_plugins()
    except Exception as exc:  # a broken plugin must not stop the robots that do work
        log.warning("third-party plugin registration failed: %s", exc)
    import lerobot_armory.robot.armory_sim.config_armory_sim  # noqa: F401
    import lerobot_armory.robot.piper.config_piper  # noqa: F401


def read_credentials(cfg: ClientConfig) -> tuple[bytes | None, str]:
    """The CA certificate and the token the command line points at."""
    tls_ca = None
    if cfg.tls_ca:
        try:
            tls_ca = Path(cfg.tls_ca).read_bytes()
        except OSError as exc:
            raise ConfigError("tls_ca", f"cannot read {cfg.tls_ca}: {exc}") from None
    token = ""
    if cfg.auth_token_file:
        try:
            lines = [ln.split("#", 1)[0].strip() for ln in Path(cfg.auth_token_file).read_text().splitlines()]
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError("auth_token_file", f"cannot read {cfg.auth_token_file}: {exc}") from None
        token = next((ln.split()[-1] for ln in lines if ln), "")
        if not token:
            raise ConfigError("auth_token_file", f"{cfg.auth_token_file} holds no token")
    return tls_ca, token


def default_robot_id(cfg: ClientConfig) -> str:
    return cfg.robot_id or getattr(cfg.robot, "id", None) or f"{cfg.robot.type}-{socket.gethostname()}-{os.getpid()}"


def run_client(cfg: ClientConfig) -> dict[str, Any]:
    """Build the robot, run the loop, always leave the robot disconnected; returns the stats."""
    from lerobot.robots.utils import make_robot_from_config

    cfg.validate()
    logging.basicConfig(level=cfg.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    robot = make_robot_from_config(cfg.robot)
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    identity = RobotIdentity(default_robot_id(cfg), cfg.fps, cfg.h_min, cfg.h_max, cfg.weight, cfg.tier, cfg.task)
    backoff = Backoff(cfg.backoff.initial_s, cfg.backoff.max_s, cfg.give_up_s)
    tls_ca, token = read_credentials(cfg)
    client = ArmoryClient(
        cfg.server_address,
        identity,
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=lambda vector: robot.send_action(fmap.to_action(vector)),
        jpeg_quality=cfg.jpeg_quality,
        backoff=backoff,
        tls_ca=tls_ca,
        token=token,
    )
    previous = signal.signal(signal.SIGTERM, lambda *_: client.stop())
    robot.connect()
    try:
        try:
            client.connect()
            if client.connection is not None:
                names = client.connection.registration.action_names if client.connection.registration else []
                if len(names) != len(fmap.action_keys):
                    raise RegistrationRefused(
                        f"the policy's actions ({len(names)}: {', '.join(names)}) do not fit the robot's "
                        f"({len(fmap.action_keys)}: {', '.join(fmap.action_keys)})"
                    )
            stats = client.run(cfg.duration_s)
        except KeyboardInterrupt:
            log.info("interrupted: holding the robot and disconnecting")
            stats = client.stats()
    finally:
        client.close()
        robot.disconnect()
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
    print(summary)
    return stats


def _run(cfg: ClientConfig) -> None:
    try:
        run_client(cfg)
    except (RegistrationRefused, ConnectionError) as exc:
        print(f"lerobot-armory-client: {exc}", file=sys.stderr)
        sys.exit(1)


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    register_robot_types()
    cfg = parse_or_exit(ClientConfig, argv, "lerobot-armory-client")
    run_or_exit(_run, cfg, "lerobot-armory-client")


if __name__ == "__main__":
    main()

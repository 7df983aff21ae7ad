"""Config of the simulated robot: ``--robot.type=armory_sim``."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.robots.config import RobotConfig

from lerobot_armory.errors import ConfigError


@RobotConfig.register_subclass("armory_sim")
@dataclass
class ArmorySimConfig(RobotConfig):
    """A simulated 2-D reacher with one camera (no download, no display).

    Attributes:
        scene: ``static`` (fixed targets) or ``dynamic`` (moving targets; stale actions miss).
        camera: camera name (the policy feature is ``observation.images.<camera>``).
        image_size: square image side, pixels.
        max_speed: effector speed, workspace units per second.
        target_speed: dynamic targets' speed, units per second.
        success_radius: touching distance.
        attempt_s: seconds per target before it counts as failed and a new one appears.
        seed: world seed.
    """

    scene: str = "static"
    camera: str = "front"
    image_size: int = 64
    max_speed: float = 1.5
    target_speed: float = 0.5
    success_radius: float = 0.12
    attempt_s: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.scene not in ("static", "dynamic"):
            raise ConfigError("robot.scene", f"must be static or dynamic, got {self.scene!r}")
        if self.image_size < 8:
            raise ConfigError("robot.image_size", f"must be >= 8, got {self.image_size}")
        for name in ("max_speed", "success_radius", "attempt_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"robot.{name}", f"must be > 0, got {getattr(self, name)}")
        if self.target_speed < 0:
            raise ConfigError("robot.target_speed", f"must be >= 0, got {self.target_speed}")

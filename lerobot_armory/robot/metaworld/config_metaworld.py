"""Config of the MetaWorld robot: ``--robot.type=metaworld``."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.robots.config import RobotConfig

from lerobot_armory.errors import ConfigError
from lerobot_armory.robot.metaworld.tasks import TASKS

# Evaluation seeds start here; demonstrations use seeds below (benchmarks/tasks/record_demos.py).
EVAL_SEED_BASE = 1000


@RobotConfig.register_subclass("metaworld")
@dataclass
class MetaWorldRobotConfig(RobotConfig):
    """A simulated Sawyer arm in MetaWorld (MuJoCo), one task, episode after episode.

    Attributes:
        task: ``push`` (static) or ``reach-moving`` (dynamic: the target circles).
        seed: the first episode's seed; episode ``k`` uses ``seed + k`` (evaluation seeds are
            1000 and up, never a demonstration's).
        episodes: stop after this many episodes (0: run until the client stops). After the last
            one the arm holds and :attr:`MetaWorldRobot.finished` is set.
        image_size: add the corner camera at this square size (0: state only). Rendering is
            software (``MUJOCO_GL=egl``) here: 100-200 ms a 96² frame on 2 busy cores, so a camera
            robot needs a low fps; the state-only robot steps in ~2 ms.
        camera: the camera's name (the policy feature is ``observation.images.<camera>``).
    """

    task: str = "push"
    seed: int = EVAL_SEED_BASE
    episodes: int = 0
    image_size: int = 0
    camera: str = "corner"

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ConfigError("robot.task", f"unknown MetaWorld task {self.task!r}: known tasks are {', '.join(sorted(TASKS))}")
        if self.seed < 0:
            raise ConfigError("robot.seed", f"must be >= 0, got {self.seed}")
        if self.episodes < 0:
            raise ConfigError("robot.episodes", f"must be >= 0 (0: no limit), got {self.episodes}")
        if self.image_size and not 16 <= self.image_size <= 480:
            raise ConfigError("robot.image_size", f"must be 0 (no camera) or 16..480, got {self.image_size}")

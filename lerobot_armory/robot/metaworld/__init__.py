"""A real simulator as a robot: MetaWorld tasks (``--robot.type=metaworld``)."""

from lerobot_armory.robot.metaworld.config_metaworld import EVAL_SEED_BASE, MetaWorldRobotConfig
from lerobot_armory.robot.metaworld.metaworld_robot import MetaWorldRobot

__all__ = ["EVAL_SEED_BASE", "MetaWorldRobotConfig", "MetaWorldRobot"]

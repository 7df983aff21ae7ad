"""Simulated robots for fleets without hardware (``--robot.type=armory_sim``)."""

from lerobot_armory.robot.armory_sim.armory_sim import ArmorySim
from lerobot_armory.robot.armory_sim.config_armory_sim import ArmorySimConfig
from lerobot_armory.robot.armory_sim.world import SCENES, ArmorySimEnv, WorldParams

__all__ = ["SCENES", "ArmorySim", "ArmorySimConfig", "ArmorySimEnv", "WorldParams"]

"""LeRobot policy types shipped with lerobot-armory (registered on import)."""

from lerobot_armory.policies.armory_planner.configuration_armory_planner import ArmoryPlannerConfig

__all__ = ["ArmoryPlannerConfig"]

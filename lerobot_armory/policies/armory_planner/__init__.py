"""An analytic chunk planner for the ``armory_sim`` tasks, packaged as a LeRobot policy type."""

from lerobot_armory.policies.armory_planner.configuration_armory_planner import ArmoryPlannerConfig

__all__ = ["ArmoryPlannerConfig"]

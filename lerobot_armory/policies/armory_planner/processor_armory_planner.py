"""Pre/post-processors of ``armory_planner``: LeRobot's default scaffold with identity normalisation."""

from __future__ import annotations

from typing import Any

from lerobot.processor.factory import make_default_pre_post_processors

from lerobot_armory.policies.armory_planner.configuration_armory_planner import ArmoryPlannerConfig


def make_armory_planner_pre_post_processors(config: ArmoryPlannerConfig, dataset_stats: dict | None = None) -> tuple[Any, Any]:
    """Rename -> batch -> device -> (identity) normalise, and back to the CPU."""
    return make_default_pre_post_processors(config, dataset_stats, normalizer_device=config.device)

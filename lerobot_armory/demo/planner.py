"""The analytic ``armory_planner`` (solves the ``armory_sim`` tasks when served on time): one camera, 2-D state."""

from __future__ import annotations

import json
from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.policies.layout import SIDECAR


def make_planner_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_armory.policies.armory_planner.configuration_armory_planner import ArmoryPlannerConfig
    from lerobot_armory.policies.armory_planner.modeling_armory_planner import ArmoryPlannerPolicy

    if len(cameras) != 1 or cfg.state_dim != 2 or (cfg.action_dim or 2) != 2:
        raise ConfigError("kind", "the planner works on armory_sim: one camera, state_dim=2, action_dim=2")
    camera = f"observation.images.{cameras[0]}"
    config = ArmoryPlannerConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
            camera: PolicyFeature(FeatureType.VISUAL, (3, cfg.image_size, cfg.image_size)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
        chunk_size=cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
        camera=camera,
        device="cpu",
    )
    policy = ArmoryPlannerPolicy(config)
    pre, post = make_pre_post_processors(config)
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    sidecar = {"action_names": ["x.pos", "y.pos"], "made_by": "lerobot-armory-make-demo-policy", "kind": "planner"}
    (out / SIDECAR).write_text(json.dumps(sidecar, indent=2) + "\n")
    return out

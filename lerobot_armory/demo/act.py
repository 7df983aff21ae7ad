"""A small ACT with random weights (``pretrained_backbone_weights=None``: no ImageNet download; deterministic at inference)."""

from __future__ import annotations

from pathlib import Path

from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.demo.common import policy_features, save_policy


def make_act_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the ACT policy of ``cfg``; returns its directory."""
    import torch
    from lerobot.configs.types import NormalizationMode
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    inputs, outputs = policy_features("ACT", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size)
    action_dim = outputs["action"].shape[0]
    torch.manual_seed(cfg.seed)
    config = ACTConfig(
        input_features=inputs,
        output_features=outputs,
        chunk_size=cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
        pretrained_backbone_weights=None,  # offline: the default would download ImageNet weights
        dim_model=cfg.dim_model,
        dim_feedforward=4 * cfg.dim_model,
        n_encoder_layers=cfg.n_encoder_layers,
        n_decoder_layers=1,
        device="cpu",
        normalization_mapping={
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        },
    )
    policy = ACTPolicy(config)
    stats = {
        "observation.state": {"mean": torch.zeros(cfg.state_dim), "std": torch.ones(cfg.state_dim)},
        "action": {"mean": torch.zeros(action_dim), "std": torch.ones(action_dim)},
    }
    for cam in cameras:
        stats[f"observation.images.{cam}"] = {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)}
    return save_policy(Path(cfg.output), policy, config, stats, {"kind": "act", "random_weights": True, "seed": cfg.seed})

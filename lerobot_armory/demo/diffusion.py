"""A tiny Diffusion Policy with random weights: LeRobot's ``DiffusionConfig`` / ``DiffusionPolicy``
and its own pre/post-processors, built offline.

    lerobot-armory-make-demo-policy --kind=diffusion --n_obs_steps=2 --output=out/diffusion-tiny

- ``pretrained_backbone_weights=None``: the ResNet-18 image encoder starts random (the default
  downloads ImageNet weights); no ``crop_shape``, so any image size fits.
- A 1-D U-Net of two stages (``down_dims=(32, 64)``) and 4 denoising steps: a batch in
  milliseconds on a CPU.
- ``noise_scheduler_type="DDIM"``: LeRobot's ``predict_action_chunk(batch, noise=...)`` only
  fixes the *initial* noise; its default DDPM scheduler then draws fresh noise in every
  ``step()`` (the posterior variance), so two calls with the same ``noise`` differ. DDIM's step
  (eta 0) adds none, so the same ``noise`` ``(B, horizon, action_dim)`` gives the same chunk:
  each robot's chunk can be seeded.
- ``n_action_steps`` is the chunk size: ``predict_action_chunk`` returns
  ``(B, n_action_steps, action_dim)``, the horizon's slice from the current observation on.
  The horizon is the smallest multiple of the U-Net's downsampling factor (LeRobot checks
  ``horizon % 2**len(down_dims) == 0``) that holds ``n_obs_steps - 1 + chunk_size`` actions.

The policy reads ``n_obs_steps`` observations per call: state ``(B, n_obs_steps, D)`` and images
``(B, n_obs_steps, C, H, W)`` (also at ``n_obs_steps=1``: ``generate_actions`` asserts the time
axis), so whoever serves it keeps each robot's observation history.
"""

from __future__ import annotations

from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features, unit_stats, save_policy
from lerobot_armory.demo.config import DemoPolicyConfig

DOWN_DIMS = (32, 64)
NUM_INFERENCE_STEPS = 4


def make_diffusion_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the tiny Diffusion Policy of ``cfg``; returns its directory."""
    import torch

    try:
        from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
        from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
        from lerobot.utils.import_utils import require_package

        require_package("diffusers", extra="diffusion")
    except ImportError as exc:
        raise ConfigError("kind", f"diffusion: {exc}") from None
    if cfg.n_obs_steps < 1:
        raise ConfigError("n_obs_steps", f"must be >= 1, got {cfg.n_obs_steps}")
    inputs, outputs = policy_features("diffusion", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size)
    factor = 2 ** len(DOWN_DIMS)
    horizon = -(-(cfg.n_obs_steps - 1 + cfg.chunk_size) // factor) * factor
    config = DiffusionConfig(
        input_features=inputs,
        output_features=outputs,
        n_obs_steps=cfg.n_obs_steps,
        horizon=horizon,
        n_action_steps=cfg.chunk_size,
        pretrained_backbone_weights=None,  # offline: the default would download ImageNet weights
        crop_shape=None,
        down_dims=DOWN_DIMS,
        diffusion_step_embed_dim=32,
        spatial_softmax_num_keypoints=8,
        noise_scheduler_type="DDIM",  # deterministic given the initial noise (module docstring)
        num_inference_steps=NUM_INFERENCE_STEPS,
        device="cpu",
    )
    torch.manual_seed(cfg.seed)
    policy = DiffusionPolicy(config)
    extra = {"kind": "diffusion", "random_weights": True, "seed": cfg.seed, "n_obs_steps": cfg.n_obs_steps}
    return save_policy(Path(cfg.output), policy, config, unit_stats(inputs, outputs), extra)

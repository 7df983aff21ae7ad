"""A tiny VQ-BeT with random weights: LeRobot's ``VQBeTConfig`` / ``VQBeTPolicy`` and its own
pre/post-processors, built offline.

    lerobot-armory-make-demo-policy --kind=vqbet --n_obs_steps=2 --output=out/vqbet-tiny

- ``pretrained_backbone_weights=None``: the ResNet-18 image encoder starts random (the default
  downloads ImageNet weights); no ``crop_shape``, so any image size fits. VQ-BeT takes exactly
  one camera.
- A residual VQ of 8 codes of 32 and a one-layer GPT 64 wide; ``action_chunk_size`` is the chunk
  size, so ``predict_action_chunk`` returns ``(B, chunk_size, action_dim)``.
- The residual VQ is marked as trained (``discretized``): its codebook is random like every other
  weight here, and LeRobot's ``select_action`` would otherwise warn on every call.

Stochastic: the codes are drawn with ``torch.multinomial`` and there is no noise argument.
``predict_action_chunk`` reads the observations only from the policy's queues
(``policy._queues``: the last ``n_obs_steps`` of each, images stacked under
``observation.images``), which ``select_action`` fills; whoever serves it per robot fills them
with that robot's history before each call.
"""

from __future__ import annotations

from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features, unit_stats, save_policy
from lerobot_armory.demo.config import DemoPolicyConfig


def make_vqbet_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the tiny VQ-BeT of ``cfg``; returns its directory."""
    import torch
    from lerobot.policies.vqbet.configuration_vqbet import VQBeTConfig
    from lerobot.policies.vqbet.modeling_vqbet import VQBeTPolicy

    if len(cameras) != 1:
        raise ConfigError("cameras", f"vqbet takes exactly one camera, got {len(cameras)}")
    if cfg.n_obs_steps < 1:
        raise ConfigError("n_obs_steps", f"must be >= 1, got {cfg.n_obs_steps}")
    inputs, outputs = policy_features("vqbet", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size)
    n_action_pred_token = 3  # LeRobot's default
    config = VQBeTConfig(
        input_features=inputs,
        output_features=outputs,
        n_obs_steps=cfg.n_obs_steps,
        n_action_pred_token=n_action_pred_token,
        action_chunk_size=cfg.chunk_size,
        pretrained_backbone_weights=None,  # offline: the default would download ImageNet weights
        crop_shape=None,
        spatial_softmax_num_keypoints=8,
        vqvae_n_embed=8,
        vqvae_embedding_dim=32,
        vqvae_enc_hidden_dim=32,
        # the GPT's sequence: an image, a state and an action-query token per observation step,
        # then n_action_pred_token - 1 more query tokens
        gpt_block_size=max(64, 3 * cfg.n_obs_steps + n_action_pred_token - 1),
        gpt_input_dim=64,
        gpt_output_dim=64,
        gpt_n_layer=1,
        gpt_n_head=2,
        gpt_hidden_dim=64,
        device="cpu",
    )
    torch.manual_seed(cfg.seed)
    policy = VQBeTPolicy(config)
    policy.vqbet.action_head.vqvae_model.discretized.fill_(True)
    extra = {"kind": "vqbet", "random_weights": True, "seed": cfg.seed, "n_obs_steps": cfg.n_obs_steps}
    return save_policy(Path(cfg.output), policy, config, unit_stats(inputs, outputs), extra)

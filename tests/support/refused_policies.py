"""Tiny LeRobot policies of types the server refuses (built offline, random weights), to show
each refusal is one line at start-up."""

from __future__ import annotations

from pathlib import Path


def _features(image_key: str, size: int = 32):
    from lerobot.configs.types import FeatureType, PolicyFeature

    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (2,)), image_key: PolicyFeature(FeatureType.VISUAL, (3, size, size))}
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (2,))}


def _save(policy, config, out: Path) -> Path:
    import torch
    from lerobot.policies.factory import make_pre_post_processors

    stats = {k: {"mean": torch.zeros(2), "std": torch.ones(2), "min": -torch.ones(2), "max": torch.ones(2)} for k in ("observation.state", "action")}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out


def make_tdmpc(out: Path) -> Path:
    from lerobot.policies.tdmpc.configuration_tdmpc import TDMPCConfig
    from lerobot.policies.tdmpc.modeling_tdmpc import TDMPCPolicy

    inputs, outputs = _features("observation.image", 64)  # TD-MPC reads one camera, "observation.image"
    config = TDMPCConfig(
        input_features=inputs, output_features=outputs, horizon=5, n_action_steps=5, n_action_repeats=1, latent_dim=16,
        mlp_dim=32, state_encoder_hidden_dim=32, image_encoder_hidden_dim=8, q_ensemble_size=2, n_gaussian_samples=16,
        n_pi_samples=4, n_elites=4, cem_iterations=2, device="cpu",
    )  # fmt: skip
    return _save(TDMPCPolicy(config), config, out)


def make_gaussian_actor(out: Path) -> Path:
    from lerobot.policies.gaussian_actor.configuration_gaussian_actor import ActorNetworkConfig, GaussianActorConfig
    from lerobot.policies.gaussian_actor.modeling_gaussian_actor import GaussianActorPolicy

    inputs, outputs = _features("observation.images.front", 64)
    config = GaussianActorConfig(
        input_features=inputs, output_features=outputs, latent_dim=16, state_encoder_hidden_dim=16, image_encoder_hidden_dim=8,
        actor_network_kwargs=ActorNetworkConfig(hidden_dims=[32, 32]), device="cpu",
    )  # fmt: skip
    return _save(GaussianActorPolicy(config), config, out)


REFUSED = {"tdmpc": make_tdmpc, "gaussian_actor": make_gaussian_actor}

"""What every demo builder shares: the policy's features and the sidecar it writes."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.policies.layout import SIDECAR


def policy_features(
    policy: str,
    chunk_size: int,
    state_dim: int,
    action_dim: int | None,
    cameras: Sequence[str],
    image_size: int,
    max_dim: int | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Checked ``(input_features, output_features)`` of a demo policy: ``observation.state``, one
    ``observation.images.<camera>`` per camera (``image_size``², as armory_sim sends them), the
    action (``action_dim``, default ``state_dim``). ``max_dim`` caps both vector sizes."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    if not cameras:
        raise ConfigError("cameras", f"{policy} needs at least one camera")
    action_dim = action_dim or state_dim
    for field, value in (("chunk_size", chunk_size), ("state_dim", state_dim), ("action_dim", action_dim), ("image_size", image_size)):
        if value < 1:
            raise ConfigError(field, f"must be >= 1, got {value}")
    if max_dim is not None and max(state_dim, action_dim) > max_dim:
        raise ConfigError("state_dim", f"{policy} takes at most {max_dim} state and {max_dim} action dimensions")
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    for cam in cameras:
        inputs[f"observation.images.{cam}"] = PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (action_dim,))}


def write_sidecar(out: Path, action_dim: int, extra: dict) -> None:
    names = {"action_names": [f"action_{k}" for k in range(action_dim)], "made_by": "lerobot-armory-make-demo-policy"}
    (out / SIDECAR).write_text(json.dumps({**names, **extra}, indent=2) + "\n")


def unit_stats(inputs: dict[str, Any], outputs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Dataset statistics for every feature of ``inputs`` and ``outputs``, whatever normalisation
    the policy applies: vectors in [-1, 1] (armory_sim's positions; mean 0, std 1, min/max and
    quantiles ±1), images in [0, 1] (mean 0.5, std 0.25 per channel, min 0, max 1)."""
    import torch
    from lerobot.configs.types import FeatureType

    stats: dict[str, dict[str, Any]] = {}
    for key, feature in {**inputs, **outputs}.items():
        if feature.type == FeatureType.VISUAL:
            c = feature.shape[0]
            stats[key] = {
                "mean": torch.full((c, 1, 1), 0.5), "std": torch.full((c, 1, 1), 0.25),
                "min": torch.zeros(c, 1, 1), "max": torch.ones(c, 1, 1),
            }  # fmt: skip
        else:
            ones = torch.ones(feature.shape[0])
            stats[key] = {"mean": 0 * ones, "std": ones, "min": -ones, "max": ones, "q01": -ones, "q99": ones}
    return stats


def save_policy(out: Path, policy: Any, config: Any, stats: dict[str, Any], sidecar: dict) -> Path:
    """Save a built policy as ``--policy.path`` loads it: the weights, LeRobot's pre/post-processors
    made with ``stats``, and our sidecar (the action names and how it was built)."""
    from lerobot.policies.factory import make_pre_post_processors

    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    write_sidecar(out, config.output_features["action"].shape[0], sidecar)
    return out

"""``lerobot-armory-make-demo-policy``: a random-weight LeRobot policy saved as a normal policy dir.

Built entirely offline, with its pre/post-processors, so ``--policy.path=DIR`` loads it through the
very same code path as a hub policy. Kinds: a small ACT (``pretrained_backbone_weights=None``: no
ImageNet download; deterministic at inference), π0.5 at ``--size=tiny|full`` (LeRobot's own
classes, a stand-in tokenizer inside DIR: ``server/demo_pi05.py``), a tiny SmolVLA (LeRobot's own
classes, a stand-in VLM config and tokenizer inside DIR: ``server/demo_smolvla.py``) and the
analytic planner.

    lerobot-armory-make-demo-policy --output=out/demo-policy
    lerobot-armory-make-demo-policy --kind=pi05 --size=tiny --output=out/pi05-tiny
    lerobot-armory-make-demo-policy --kind=smolvla --output=out/smolvla-tiny
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.server.engine import SIDECAR

KINDS = ("act", "pi05", "smolvla", "planner")


@dataclass
class DemoPolicyConfig:
    """Options of the demo policy.

    Attributes:
        output: directory to write (created).
        kind: ``act`` (small random-weight ACT), ``pi05`` (LeRobot's π0.5, random weights),
            ``smolvla`` (LeRobot's SmolVLA, tiny, random weights) or ``planner`` (the analytic
            ``armory_planner`` that solves the ``armory_sim`` tasks when served on time; one
            camera, 2-D state).
        size: π0.5 only: ``tiny`` (registered ``armory_tiny`` Gemma size, runs on a CPU), ``narrow``
            (the real depths at tiny widths: ``armory_narrow``) or
            ``full`` (PaliGemma gemma_2b + expert gemma_300m, the real sizes).
        dtype: π0.5 only: ``float32`` or ``bfloat16`` weights.
        chunk_size: H, actions per chunk.
        state_dim: length of ``observation.state``.
        action_dim: length of each action (default: state_dim).
        cameras: comma-separated camera names (features ``observation.images.<name>``).
        image_size: square image side in pixels.
        dim_model: transformer width (small keeps CPU inference fast).
        n_encoder_layers: transformer encoder layers.
        seed: torch seed for the random weights.
        device: π0.5 only: where the random weights are created (``cuda``: seconds instead of
            minutes for the full size); the directory is the same either way.
    """

    output: str = "out/demo-policy"
    kind: str = "act"
    size: str = "tiny"
    dtype: str = "float32"
    chunk_size: int = 20
    state_dim: int = 2
    action_dim: int | None = None
    cameras: str = "front"
    image_size: int = 64
    dim_model: int = 128
    n_encoder_layers: int = 2
    seed: int = 0
    device: str = "cpu"


def make_demo_policy(cfg: DemoPolicyConfig) -> Path:
    """Build and save the policy; returns its directory."""
    import torch
    from lerobot.configs.types import NormalizationMode
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    if cfg.kind not in KINDS:
        raise ConfigError("kind", f"must be one of {', '.join(KINDS)}, got {cfg.kind!r}")
    cameras = [c.strip() for c in cfg.cameras.split(",") if c.strip()]
    if cfg.kind in ("act", "planner") and (cfg.size, cfg.dtype) != ("tiny", "float32"):
        raise ConfigError("size" if cfg.size != "tiny" else "dtype", f"--size and --dtype apply to pi05 (and smolvla), not to {cfg.kind}")
    if cfg.kind == "planner":
        return _make_planner(cfg, cameras)
    if cfg.kind == "pi05":
        from lerobot_armory.server.demo_pi05 import make_pi05_policy

        out = make_pi05_policy(
            cfg.output, cfg.size, cfg.chunk_size, cfg.state_dim, cfg.action_dim, tuple(cameras), cfg.image_size, cfg.seed, cfg.dtype,
            cfg.device,
        )
        _write_sidecar(out, cfg.action_dim or cfg.state_dim, {"kind": "pi05", "size": cfg.size, "random_weights": True, "seed": cfg.seed})
        return out
    if cfg.kind == "smolvla":
        from lerobot_armory.server.demo_smolvla import make_smolvla_policy

        if cfg.size != "tiny" or cfg.dtype != "float32":
            raise ConfigError("size", "SmolVLA is built at size=tiny, dtype=float32 only")
        out = make_smolvla_policy(
            cfg.output, cfg.chunk_size, cfg.state_dim, cfg.action_dim, tuple(cameras), cfg.image_size, cfg.seed
        )
        extra = {"kind": "smolvla", "size": "tiny", "random_weights": True, "seed": cfg.seed}
        _write_sidecar(out, cfg.action_dim or cfg.state_dim, extra)
        return out
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
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    _write_sidecar(out, action_dim, {"kind": "act", "random_weights": True, "seed": cfg.seed})
    return out


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


def _write_sidecar(out: Path, action_dim: int, extra: dict) -> None:
    names = {"action_names": [f"action_{k}" for k in range(action_dim)], "made_by": "lerobot-armory-make-demo-policy"}
    (out / SIDECAR).write_text(json.dumps({**names, **extra}, indent=2) + "\n")


def _make_planner(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
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


def _run(cfg: DemoPolicyConfig) -> None:
    out = make_demo_policy(cfg)
    size_mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 1e6
    what = {
        "planner": "analytic armory_planner policy",
        "act": "ACT policy (random weights)",
        "smolvla": "SmolVLA tiny policy (random weights, stand-in VLM config and tokenizer)",
    }.get(cfg.kind, f"π0.5 {cfg.size} policy (random weights, stand-in tokenizer)")
    print(f"demo {what}, {size_mb:.1f} MB, written to {out}; serve it with --policy.path={out}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(DemoPolicyConfig, argv, "lerobot-armory-make-demo-policy")
    run_or_exit(_run, cfg, "lerobot-armory-make-demo-policy")


if __name__ == "__main__":
    main()

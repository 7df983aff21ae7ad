"""``lerobot-armory-make-demo-policy``: a random-weight LeRobot policy saved as a normal policy dir.

Built entirely offline, with its pre/post-processors, so ``--policy.path=DIR`` loads it through the
very same code path as a hub policy. Kinds, each LeRobot's own classes at a tiny size unless said:

- ``act``: a small ACT (``pretrained_backbone_weights=None``: no ImageNet download; deterministic
  at inference);
- ``pi05`` and ``pi0`` at ``--size=tiny|narrow|full`` (a registered tiny Gemma size and a stand-in
  tokenizer inside DIR: :mod:`.pi05`, :mod:`.pi0`);
- ``pi0_fast`` (stand-in text and FAST action tokenizers inside DIR, so that every generated
  token decodes: :mod:`.pi0_fast`);
- ``smolvla`` (a stand-in VLM config and tokenizer inside DIR: :mod:`.smolvla`);
- ``diffusion`` (DDIM, so the initial noise fixes the chunk; ``--n_obs_steps``: :mod:`.diffusion`);
- ``vqbet`` (one camera; ``--n_obs_steps``: :mod:`.vqbet`);
- ``multi_task_dit`` (a stand-in CLIP inside DIR; ``--n_obs_steps``: :mod:`.multi_task_dit`);
- ``xvla`` (Florence-2 from its config, a stand-in tokenizer inside DIR: :mod:`.xvla`);
- ``planner``: the analytic planner (:mod:`.planner`).

Each kind is one builder in :data:`BUILDERS`.

    lerobot-armory-make-demo-policy --output=out/demo-policy
    lerobot-armory-make-demo-policy --kind=pi05 --size=tiny --output=out/pi05-tiny
    lerobot-armory-make-demo-policy --kind=smolvla --output=out/smolvla-tiny
    lerobot-armory-make-demo-policy --kind=diffusion --n_obs_steps=2 --output=out/diffusion-tiny
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import write_sidecar
from lerobot_armory.demo.config import DemoPolicyConfig


def _build_act(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.act import make_act_policy

    return make_act_policy(cfg, cameras)


def _build_pi05(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.pi05 import make_pi05_policy

    out = make_pi05_policy(
        cfg.output, cfg.size, cfg.chunk_size, cfg.state_dim, cfg.action_dim, tuple(cameras), cfg.image_size, cfg.seed, cfg.dtype,
        cfg.device,
    )
    write_sidecar(out, cfg.action_dim or cfg.state_dim, {"kind": "pi05", "size": cfg.size, "random_weights": True, "seed": cfg.seed})
    return out


def _build_pi0(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.pi0 import make_pi0_policy

    out = make_pi0_policy(
        cfg.output, cfg.size, cfg.chunk_size, cfg.state_dim, cfg.action_dim, tuple(cameras), cfg.image_size, cfg.seed, cfg.dtype,
        cfg.device,
    )
    write_sidecar(out, cfg.action_dim or cfg.state_dim, {"kind": "pi0", "size": cfg.size, "random_weights": True, "seed": cfg.seed})
    return out


def _build_pi0_fast(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.pi0_fast import make_pi0_fast_policy

    return make_pi0_fast_policy(cfg, cameras)


def _build_smolvla(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.smolvla import make_smolvla_policy

    if cfg.dtype != "float32":
        raise ConfigError("dtype", "SmolVLA is built in float32 only (as LeRobot builds it from its configuration)")
    out = make_smolvla_policy(cfg.output, cfg.chunk_size, cfg.state_dim, cfg.action_dim, tuple(cameras), cfg.image_size, cfg.seed, cfg.size)
    write_sidecar(out, cfg.action_dim or cfg.state_dim, {"kind": "smolvla", "size": cfg.size, "random_weights": True, "seed": cfg.seed})
    return out


def _build_diffusion(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.diffusion import make_diffusion_policy

    return make_diffusion_policy(cfg, cameras)


def _build_vqbet(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.vqbet import make_vqbet_policy

    return make_vqbet_policy(cfg, cameras)


def _build_multi_task_dit(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.multi_task_dit import make_multi_task_dit_policy

    return make_multi_task_dit_policy(cfg, cameras)


def _build_xvla(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.xvla import make_xvla_policy

    return make_xvla_policy(cfg, cameras)


def _build_planner(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    from lerobot_armory.demo.planner import make_planner_policy

    return make_planner_policy(cfg, cameras)


# kind -> builder (each imports its LeRobot classes only when called); a new kind is one module
# under demo/ and one entry here.
BUILDERS: dict[str, Callable[[DemoPolicyConfig, list[str]], Path]] = {
    "act": _build_act,
    "pi05": _build_pi05,
    "pi0": _build_pi0,
    "pi0_fast": _build_pi0_fast,
    "smolvla": _build_smolvla,
    "diffusion": _build_diffusion,
    "vqbet": _build_vqbet,
    "multi_task_dit": _build_multi_task_dit,
    "xvla": _build_xvla,
    "planner": _build_planner,
}
KINDS = tuple(BUILDERS)
# what --size and --dtype apply to
SIZED_KINDS = ("pi05", "pi0", "smolvla")
# what --n_obs_steps applies to (policies that read an observation history)
HISTORY_KINDS = ("diffusion", "vqbet", "multi_task_dit")


def make_demo_policy(cfg: DemoPolicyConfig) -> Path:
    """Build and save the policy; returns its directory."""
    if cfg.kind not in BUILDERS:
        raise ConfigError("kind", f"must be one of {', '.join(KINDS)}, got {cfg.kind!r}")
    cameras = [c.strip() for c in cfg.cameras.split(",") if c.strip()]
    if cfg.kind not in SIZED_KINDS and (cfg.size, cfg.dtype) != ("tiny", "float32"):
        raise ConfigError("size" if cfg.size != "tiny" else "dtype", f"--size and --dtype apply to pi05, pi0 (and smolvla), not to {cfg.kind}")
    if cfg.kind not in HISTORY_KINDS and cfg.n_obs_steps != DemoPolicyConfig.n_obs_steps:
        raise ConfigError("n_obs_steps", f"applies to {', '.join(HISTORY_KINDS)}, not to {cfg.kind}")
    return BUILDERS[cfg.kind](cfg, cameras)


def _run(cfg: DemoPolicyConfig) -> None:
    out = make_demo_policy(cfg)
    size_mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 1e6
    what = {
        "planner": "analytic armory_planner policy",
        "act": "ACT policy (random weights)",
        "pi05": f"π0.5 {cfg.size} policy (random weights, stand-in tokenizer)",
        "pi0": f"π0 {cfg.size} policy (random weights, stand-in tokenizer)",
        "pi0_fast": "π0-FAST tiny policy (random weights, stand-in text and FAST tokenizers)",
        "smolvla": "SmolVLA tiny policy (random weights, stand-in VLM config and tokenizer)",
        "diffusion": f"Diffusion Policy tiny (random weights, DDIM, n_obs_steps={cfg.n_obs_steps})",
        "vqbet": f"VQ-BeT tiny policy (random weights, n_obs_steps={cfg.n_obs_steps})",
        "multi_task_dit": f"Multi-Task DiT tiny policy (random weights, stand-in CLIP, n_obs_steps={cfg.n_obs_steps})",
        "xvla": "X-VLA tiny policy (random weights, stand-in tokenizer)",
    }[cfg.kind]
    print(f"demo {what}, {size_mb:.1f} MB, written to {out}; serve it with --policy.path={out}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(DemoPolicyConfig, argv, "lerobot-armory-make-demo-policy")
    run_or_exit(_run, cfg, "lerobot-armory-make-demo-policy")


if __name__ == "__main__":
    main()

"""``lerobot-armory-make-demo-policy``'s options (every builder reads them)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class DemoPolicyConfig:
    """Options of the demo policy.

    Attributes:
        output: directory to write (created).
        kind: ``act`` (small random-weight ACT), ``pi05`` (LeRobot's π0.5, random weights),
            ``pi0`` (LeRobot's π0, random weights), ``pi0_fast`` (LeRobot's π0-FAST, tiny,
            stand-in text and FAST tokenizers inside), ``smolvla`` (LeRobot's SmolVLA, tiny, random
            weights), ``diffusion`` (Diffusion Policy, tiny, DDIM), ``vqbet`` (VQ-BeT, tiny; one
            camera), ``multi_task_dit`` (Multi-Task DiT, tiny, a stand-in CLIP inside),
            ``xvla`` (X-VLA, tiny Florence-2, a stand-in tokenizer inside) or ``planner`` (the
            analytic ``armory_planner`` that solves the ``armory_sim`` tasks when served on time;
            one camera, 2-D state). Every LeRobot kind but ``planner`` has random weights and is
            built offline; ``diffusion`` and ``multi_task_dit`` need LeRobot's ``diffusion`` /
            ``multi-task-dit`` extra (diffusers).
        size: π0.5, π0 and SmolVLA only: ``tiny`` (registered ``armory_tiny`` Gemma size, runs on a
            CPU), ``narrow`` (the real depths at tiny widths: ``armory_narrow``) or ``full``
            (PaliGemma gemma_2b + expert gemma_300m, the real sizes; SmolVLA: SmolVLM2-500M's).
        dtype: π0.5 and π0 only: ``float32`` or ``bfloat16`` weights (SmolVLA: ``float32``).
        chunk_size: H, actions per chunk.
        state_dim: length of ``observation.state``.
        action_dim: length of each action (default: state_dim).
        cameras: comma-separated camera names (features ``observation.images.<name>``).
        image_size: square image side in pixels.
        dim_model: ACT only: transformer width (small keeps CPU inference fast).
        n_encoder_layers: ACT only: transformer encoder layers.
        n_obs_steps: diffusion, vqbet and multi_task_dit only: observations per prediction (the
            current one and the ``n_obs_steps - 1`` before it; LeRobot's default is 2 for
            diffusion and multi_task_dit, 5 for vqbet).
        seed: torch seed for the random weights.
        device: π0.5 and π0 only: where the random weights are created (``cuda``: seconds instead of
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
    n_obs_steps: int = 2
    seed: int = 0
    device: str = "cpu"

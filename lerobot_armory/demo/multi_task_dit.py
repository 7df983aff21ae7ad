"""A tiny Multi-Task DiT with random weights: LeRobot's ``MultiTaskDiTConfig`` /
``MultiTaskDiTPolicy`` and its own pre/post-processors, with a stand-in CLIP stored inside it.

    lerobot-armory-make-demo-policy --kind=multi_task_dit --n_obs_steps=2 --output=out/mtdit-tiny

The policy builds its image and text encoders with ``CLIPVisionModel`` / ``CLIPTextModel
.from_pretrained(vision_encoder_name / text_encoder_name)`` (``openai/clip-vit-base-patch16``),
and its pre-processor tokenizes the task with ``AutoTokenizer.from_pretrained(text_encoder_name)``.
All three accept a local directory (LeRobot only checks that the name contains "clip"), so this
module writes one, ``DIR/clip``, with nothing from the hub:

- a ``CLIPModel`` with random weights (text and vision towers 32 wide, 1 layer; 32² images in 8²
  patches), whose text config names the stand-in's end-of-sequence id: CLIP pools the text at the
  first end-of-sequence token;
- the stand-in tokenizer (:mod:`.standin_tokenizer`) saved to append that token, as CLIP's own
  tokenizer does (``DIR/tokenizer`` holds the same, for the server's tokenizer override).

``config.json`` names ``DIR/clip`` by its absolute path at build time; the server points both
encoder names at the directory's own ``clip`` wherever the directory now is
(``engine/policy_engine.py``), and a plain LeRobot script loading a moved directory passes
``--policy.vision_encoder_name=NEWDIR/clip --policy.text_encoder_name=NEWDIR/clip``.

The DiT is one layer 64 wide; horizon ``n_obs_steps - 1 + chunk_size``, ``n_action_steps`` the
chunk size, so ``predict_action_chunk`` returns ``(B, chunk_size, action_dim)``; DDIM in 4 steps.
Stochastic: the initial noise is drawn inside (``torch.randn``, no noise argument).
``predict_action_chunk`` replaces the batch's observations by the policy's queues
(``policy._queues``: the last ``n_obs_steps`` states and stacked images), which ``select_action``
fills; whoever serves it per robot fills them with that robot's history before each call.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features, unit_stats, save_policy
from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.policies.layout import CLIP_DIR, TOKENIZER_DIR  # where the loader looks for them

# Sizes of the stand-in CLIP (clip-vit-base-patch16: text 512 wide, 12 layers, 77 positions;
# vision 768 wide, 12 layers, 224² images in 16² patches).
TINY_TEXT = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, max_position_embeddings=32)
TINY_VISION = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=32, patch_size=8)
VOCAB = 1024  # every id of the stand-in tokenizer is below it
PROMPT_LENGTH = 16


def make_multi_task_dit_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the tiny Multi-Task DiT of ``cfg``; returns its directory."""
    import torch

    try:
        from lerobot.policies.multi_task_dit.configuration_multi_task_dit import MultiTaskDiTConfig
        from lerobot.policies.multi_task_dit.modeling_multi_task_dit import MultiTaskDiTPolicy
        from lerobot.utils.import_utils import require_package

        require_package("diffusers", extra="multi-task-dit")
    except ImportError as exc:
        raise ConfigError("kind", f"multi_task_dit: {exc}") from None
    if cfg.n_obs_steps < 1:
        raise ConfigError("n_obs_steps", f"must be >= 1, got {cfg.n_obs_steps}")
    inputs, outputs = policy_features("multi_task_dit", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size)
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    with _quiet_transformers():
        clip = build_standin_clip(out / CLIP_DIR, out / TOKENIZER_DIR)
    side = TINY_VISION["image_size"]
    config = MultiTaskDiTConfig(
        input_features=inputs,
        output_features=outputs,
        n_obs_steps=cfg.n_obs_steps,
        horizon=cfg.n_obs_steps - 1 + cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
        vision_encoder_name=str(clip.resolve()),
        text_encoder_name=str(clip.resolve()),
        image_resize_shape=(side, side),  # the stand-in CLIP's image size
        image_crop_shape=None,
        tokenizer_max_length=PROMPT_LENGTH,
        hidden_dim=64,
        num_layers=1,
        num_heads=2,
        timestep_embed_dim=32,
        noise_scheduler_type="DDIM",
        num_inference_steps=4,
        device="cpu",
    )
    with _quiet_transformers():
        policy = MultiTaskDiTPolicy(config)
    # The DiT's conditioning layers start at zero (adaLN-zero), so at random init the prompt and
    # the observation have no effect on the chunk; a trained one's do. Redraw every all-zero
    # weight so that they reach the chunk, which is what the tests check per robot.
    with torch.no_grad():
        for param in policy.parameters():
            if param.ndim > 1 and not param.any():
                param.normal_(0.0, 0.05)
    extra = {"kind": "multi_task_dit", "random_weights": True, "seed": cfg.seed, "n_obs_steps": cfg.n_obs_steps}
    return save_policy(out, policy, config, unit_stats(inputs, outputs), extra)


def build_standin_clip(output: Path, tokenizer_output: Path | None = None) -> Path:
    """Write a tiny random ``CLIPModel`` and its stand-in tokenizer to ``output`` (and the
    tokenizer alone to ``tokenizer_output``); returns ``output``. Needs no network."""
    import tempfile

    from transformers import AutoTokenizer, CLIPConfig, CLIPModel

    from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer

    with tempfile.TemporaryDirectory() as tmp:
        build_standin_tokenizer(tmp, max_id=VOCAB)
        # CLIP pools the text at its end-of-sequence token: end every prompt with one.
        tokenizer = AutoTokenizer.from_pretrained(tmp, add_eos_token=True)
    tokenizer.save_pretrained(output)
    if tokenizer_output is not None:
        tokenizer.save_pretrained(tokenizer_output)
    ids = dict(pad_token_id=tokenizer.pad_token_id, bos_token_id=tokenizer.bos_token_id, eos_token_id=tokenizer.eos_token_id)
    config = CLIPConfig(
        text_config=dict(vocab_size=VOCAB, **TINY_TEXT, **ids),
        vision_config=dict(TINY_VISION),
        projection_dim=32,
    )
    CLIPModel(config).save_pretrained(output)
    return output


@contextlib.contextmanager
def _quiet_transformers() -> Iterator[None]:
    """No progress bars while the stand-in CLIP is written, and no "LOAD REPORT" while the policy
    builds: ``CLIPVisionModel`` / ``CLIPTextModel.from_pretrained`` of a ``CLIPModel`` directory
    (as of the real ``openai/clip-vit-base-patch16``) log every key of the other tower as
    unexpected."""
    from transformers.utils import logging

    level = logging.get_verbosity()
    bars = logging.is_progress_bar_enabled()
    logging.set_verbosity_error()
    logging.disable_progress_bar()
    try:
        yield
    finally:
        logging.set_verbosity(level)
        if bars:
            logging.enable_progress_bar()

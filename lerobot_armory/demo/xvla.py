"""A tiny X-VLA with random weights: LeRobot's ``XVLAConfig`` / ``XVLAPolicy`` and its own
pre/post-processors, with a stand-in tokenizer stored inside it.

    lerobot-armory-make-demo-policy --kind=xvla --output=out/xvla-tiny

X-VLA builds its Florence-2 backbone from the ``florence_config`` dict (``transformers``' own
``Florence2Config``), so a tiny one needs nothing from the hub: a DaViT vision tower of two
stages (16 and 32 wide, one block each) and a BART text model 64 wide with one encoder and one
decoder layer. Only the pre-processor's tokenizer, ``facebook/bart-large``, would download: the
stand-in tokenizer (:mod:`.standin_tokenizer`, ids below the tiny vocabulary of 1024) in
``DIR/tokenizer`` takes its place, and the server points the ``tokenizer_processor`` step there
wherever the directory has moved. The soft-prompted action transformer is one layer 64 wide;
3 flow-matching steps; ``action_mode="auto"`` pads the action to ``max_action_dim`` inside and
trims it back, so ``predict_action_chunk`` returns ``(B, chunk_size, action_dim)``.

Stochastic, and the noise cannot be given: ``predict_action_chunk(batch, noise=None)`` ignores
``noise`` and draws ``torch.randn`` itself. It takes one observation per call
(``n_obs_steps=1``); the queues it fills are never read.
"""

from __future__ import annotations

from pathlib import Path

from lerobot_armory.demo.common import policy_features, unit_stats, save_policy
from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.policies.layout import TOKENIZER_DIR  # where the loader looks for it

VOCAB = 1024
# Florence-2 (base: DaViT 4 stages up to 1024 wide, BART 768 wide with 6 + 6 layers) at tiny sizes.
TINY_FLORENCE = {
    "vision_config": dict(
        depths=[1, 1], patch_size=[7, 3], patch_stride=[4, 2], patch_padding=[3, 1], patch_prenorm=[False, True],
        embed_dim=[16, 32], num_heads=[2, 2], num_groups=[2, 2], window_size=4, projection_dim=64,
        max_position_embeddings=16, max_temporal_embeddings=4,
    ),
    "text_config": dict(
        model_type="bart", vocab_size=VOCAB, d_model=64, encoder_layers=1, decoder_layers=1,
        encoder_attention_heads=2, decoder_attention_heads=2, encoder_ffn_dim=128, decoder_ffn_dim=128,
        max_position_embeddings=256,
    ),
}  # fmt: skip
IMAGE_SIDE = 64  # images are resized (with padding) to this: 8 × 8 tokens after the two stages
MAX_DIM = 20  # LeRobot's max_action_dim; the state is padded to it too


def make_xvla_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the tiny X-VLA of ``cfg``; returns its directory."""
    import torch
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig
    from lerobot.policies.xvla.modeling_xvla import XVLAPolicy

    from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer

    inputs, outputs = policy_features("xvla", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size, max_dim=MAX_DIM)
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    tokenizer = build_standin_tokenizer(out / TOKENIZER_DIR, max_id=VOCAB)
    config = XVLAConfig(
        input_features=inputs,
        output_features=outputs,
        florence_config=TINY_FLORENCE,
        tokenizer_name=str(tokenizer.resolve()),  # the saved step names it; the server re-points it
        tokenizer_max_length=16,
        hidden_size=64,
        depth=1,
        num_heads=2,
        len_soft_prompts=4,
        num_denoising_steps=3,
        chunk_size=cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
        action_mode="auto",
        max_action_dim=MAX_DIM,
        max_state_dim=MAX_DIM,
        resize_imgs_with_padding=(IMAGE_SIDE, IMAGE_SIDE),
        device="cpu",
    )
    torch.manual_seed(cfg.seed)
    policy = XVLAPolicy(config)
    return save_policy(out, policy, config, unit_stats(inputs, outputs), {"kind": "xvla", "random_weights": True, "seed": cfg.seed})

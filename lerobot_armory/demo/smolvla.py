"""Build a SmolVLA policy directory offline: LeRobot's ``SmolVLAConfig`` / ``SmolVLAPolicy`` with
random weights, LeRobot's own SmolVLA pre/post-processors, and a tiny stand-in VLM stored inside it.

    lerobot-armory-make-demo-policy --kind=smolvla --output=out/smolvla-tiny
    lerobot-armory-server --policy.path=out/smolvla-tiny

SmolVLA builds its backbone from ``vlm_model_name`` (``HuggingFaceTB/SmolVLM2-500M-Video-Instruct``)
even with ``load_vlm_weights=False``: ``SmolVLMWithExpertModel`` calls ``AutoConfig`` and
``AutoProcessor.from_pretrained(vlm_model_name)`` (the architecture, and the tokenizer's
``<fake_token_around_image>`` / ``<global-img>`` ids), and the pre-processor's
``tokenizer_processor`` step calls ``AutoTokenizer.from_pretrained(vlm_model_name)``. Both accept
a local directory, so this module writes one, ``DIR/vlm``, with nothing from the hub:

- ``config.json``: a ``SmolVLMConfig`` at one of three sizes (:data:`SIZES`): ``tiny`` (Llama text
  model 64 wide, 2 layers, head_dim 32; SigLIP-style vision tower 32 wide, 1 layer, 32² images in
  8² patches, pixel-shuffle 2 → 4 tokens per camera), ``narrow`` (SmolVLM2-500M's depths and image
  geometry at tiny widths: kernel counts on a CPU) and ``full`` (SmolVLM2-500M's sizes: text 960
  wide, 32 layers of which SmolVLA keeps 16, 15 query heads on 5 K/V heads of 64; vision 768 wide,
  12 layers, 512² images in 16² patches, pixel-shuffle 4 → 64 tokens per camera; as its published
  configuration gives them — the file itself cannot be fetched here — with random weights: a
  model to time, not to run a robot);
- a byte-level BPE tokenizer (GPT-2 style like SmolVLM2's, so any text encodes) trained here on a
  fixed text, with SmolVLM2's special tokens and its ``fake_image_token`` / ``global_image_token`` /
  ``image_token`` names; saved with the ``SmolVLMProcessor`` that wraps it (``processor_config.json``).

``DIR/tokenizer`` holds the same tokenizer alone, so the server points the pre-processor's
``tokenizer_processor`` step there wherever the directory has been moved (``engine/policy_engine.py``).

Everything else is LeRobot's real SmolVLA code path: prefix of image, language and state tokens,
KV cache, the interleaved self/cross-attention action expert (0.75 × the VLM width), 10
flow-matching steps. Tiny: 0.24 M parameters, a batch runs in tens of milliseconds on one CPU
core; full: ≈ 450 M.

``config.json`` stores ``vlm_model_name`` as the absolute path of ``DIR/vlm`` at build time
(SmolVLA resolves it against the working directory, not the policy directory); the server points
it at the directory's own ``vlm`` wherever the directory now is (``engine/policy_engine.py``), and a plain
LeRobot script loading a moved directory passes ``vlm_model_name=NEWDIR/vlm``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features
from lerobot_armory.policies.layout import TOKENIZER_DIR, VLM_DIR  # where the loader looks for them

# SmolVLM2's special tokens (its tokenizer names the image ones as attributes SmolVLA reads).
_SPECIALS = {
    "unk_token": "<|endoftext|>",
    "bos_token": "<|im_start|>",
    "pad_token": "<|im_end|>",
    "eos_token": "<end_of_utterance>",
}
_EXTRA = {
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
    "video_token": "<video>",
}
# Text the stand-in tokenizer is trained on (SmolVLA's prompt is the task and a newline). Fixed,
# so a build is reproducible.
_CORPUS = [
    "pick up the red block and place it in the bin\n",
    "sort the bricks by colour\n",
    "reach the moving target\n",
    "touch the static target\n",
    "open the drawer and close the drawer\n",
    "push the button, fold the towel, stack the cups\n",
    "put the bowl on the plate, wipe the table\n",
    "insert the peg into the hole\n",
    "move the arm to the left, to the right, up and down\n",
    "0 1 2 3 4 5 6 7 8 9 10 20 50 100\n",
]
# Sizes of the stand-in SmolVLM (SmolVLM2-500M: text 960 wide, 32 layers, head_dim 64; vision 768
# wide, 12 layers, 512² images in 16² patches). The action expert is 0.75 × the text width.
TINY_TEXT = dict(
    hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1, head_dim=32
)
TINY_VISION = dict(
    hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=32, patch_size=8
)


@dataclass(frozen=True)
class SmolVLMSize:
    """One stand-in SmolVLM: its text and vision configurations, its pixel-shuffle factor, the VLM
    layers SmolVLA keeps (``num_vlm_layers``), the rotary range and the vocabulary (None: the
    stand-in tokenizer's own)."""

    text: dict
    vision: dict
    scale_factor: int
    vlm_layers: int
    max_positions: int = 512
    vocab_size: int | None = None
    rope_theta: float | None = None


SIZES = {
    "tiny": SmolVLMSize(TINY_TEXT, TINY_VISION, scale_factor=2, vlm_layers=2),
    # SmolVLM2-500M's depths, heads and image geometry at tiny widths (what a CPU can count).
    "narrow": SmolVLMSize(
        dict(hidden_size=120, intermediate_size=128, num_hidden_layers=32, num_attention_heads=15, num_key_value_heads=5, head_dim=16),
        dict(hidden_size=32, intermediate_size=64, num_hidden_layers=12, num_attention_heads=2, image_size=512, patch_size=16),
        scale_factor=4, vlm_layers=16, max_positions=8192,
    ),  # fmt: skip
    # SmolVLM2-500M-Video-Instruct's published sizes; SmolVLA keeps 16 of its 32 text layers.
    "full": SmolVLMSize(
        dict(hidden_size=960, intermediate_size=2560, num_hidden_layers=32, num_attention_heads=15, num_key_value_heads=5, head_dim=64),
        dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12, image_size=512, patch_size=16),
        scale_factor=4, vlm_layers=16, max_positions=8192, vocab_size=49280, rope_theta=100000.0,
    ),  # fmt: skip
}


def make_smolvla_policy(
    output: str | Path,
    chunk_size: int = 50,
    state_dim: int = 2,
    action_dim: int | None = None,
    cameras: tuple[str, ...] = ("front",),
    image_size: int = 64,
    seed: int = 0,
    size: str = "tiny",
) -> Path:
    """Build and save a random-weight SmolVLA; returns its directory.

    Args:
        output: directory to write (created).
        chunk_size: H, actions per chunk (SmolVLA's default is 50).
        state_dim / action_dim: vector sizes (padded internally to SmolVLA's 32).
        cameras: camera names; each becomes ``observation.images.<name>`` of ``image_size``².
        image_size: side of the images robots send (the model resizes and pads to the VLM's
            image size: 32² tiny, 512² narrow and full).
        seed: torch seed for the random weights.
        size: ``tiny``, ``narrow`` or ``full`` (:data:`SIZES`).
    """
    import torch

    if size not in SIZES:
        raise ConfigError("size", f"SmolVLA is built at size {', '.join(SIZES)}, got {size!r}")
    dims = SIZES[size]
    inputs, outputs = policy_features("SmolVLA", chunk_size, state_dim, action_dim, cameras, image_size, max_dim=32)
    try:
        from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
        from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
        from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors
        import num2words  # noqa: F401  (transformers' SmolVLM processor needs it; fail here, in one line)
    except ImportError as exc:
        raise ConfigError("kind", f"SmolVLA needs LeRobot's smolvla extra (pip install 'lerobot-armory[smolvla]'): {exc}") from None
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    vlm = build_standin_vlm(out / VLM_DIR, size=dims)
    tokenizer_dir = out / TOKENIZER_DIR
    _tokenizer(vlm).save_pretrained(tokenizer_dir)
    side = dims.vision["image_size"]
    config = SmolVLAConfig(
        vlm_model_name=str(vlm.resolve()),
        load_vlm_weights=False,  # random weights: the architecture comes from DIR/vlm/config.json
        num_vlm_layers=dims.vlm_layers,
        resize_imgs_with_padding=(side, side),
        chunk_size=chunk_size,
        n_action_steps=chunk_size,
        input_features=inputs,
        output_features=outputs,
        device="cpu",
    )
    torch.manual_seed(seed)
    with _quiet():
        policy = SmolVLAPolicy(config)
    # SmolVLA normalises state and action by mean/std; armory_sim's positions live in [-1, 1].
    stats = {
        "observation.state": {"mean": torch.zeros(state_dim), "std": torch.ones(state_dim)},
        "action": {"mean": torch.zeros(outputs["action"].shape[0]), "std": torch.ones(outputs["action"].shape[0])},
    }
    pre, post = make_smolvla_pre_post_processors(config, dataset_stats=stats)
    # The saved tokenizer step names DIR/tokenizer (the server re-points it wherever DIR now is).
    for step in pre.steps:
        if type(step).__name__ == "TokenizerProcessorStep":
            step.tokenizer_name = str(tokenizer_dir.resolve())
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out


def build_standin_vlm(output: str | Path, vocab_size: int = 512, size: SmolVLMSize = SIZES["tiny"]) -> Path:
    """Write a stand-in SmolVLM (``config.json``, tokenizer, ``SmolVLMProcessor``) of ``size`` to
    ``output``, a local stand-in for ``vlm_model_name``; returns ``output``. Needs no network.
    ``vocab_size`` is the stand-in tokenizer's (its ids are all the model ever sees)."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import (
        PreTrainedTokenizerFast,
        SmolVLMConfig,
        SmolVLMImageProcessor,
        SmolVLMProcessor,
        SmolVLMVideoProcessor,
    )

    specials = list(dict.fromkeys([*_SPECIALS.values(), *_EXTRA.values()]))
    bpe = Tokenizer(models.BPE())
    bpe.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=specials,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),  # every byte: any text encodes
        show_progress=False,
    )
    bpe.train_from_iterator(_CORPUS * 8, trainer=trainer)
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=bpe, extra_special_tokens=dict(_EXTRA), **_SPECIALS)
    side = size.vision["image_size"]
    processor = SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(
            size={"longest_edge": side}, max_image_size={"longest_edge": side}, do_image_splitting=False
        ),
        tokenizer=tokenizer,
        video_processor=SmolVLMVideoProcessor(),
        image_seq_len=(side // size.vision["patch_size"]) ** 2 // size.scale_factor**2,  # after the pixel shuffle
    )
    rope = {} if size.rope_theta is None else {"rope_theta": size.rope_theta}
    config = SmolVLMConfig(
        text_config=dict(
            model_type="llama",
            vocab_size=size.vocab_size or len(tokenizer),
            pad_token_id=tokenizer.pad_token_id,
            max_position_embeddings=size.max_positions,
            **rope,
            **size.text,
        ),
        vision_config=dict(size.vision),
        scale_factor=size.scale_factor,
        image_token_id=tokenizer.convert_tokens_to_ids(_EXTRA["image_token"]),
        pad_token_id=tokenizer.pad_token_id,
    )
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    processor.save_pretrained(out)
    config.save_pretrained(out)
    return out


def _tokenizer(vlm: Path):
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(vlm)


@contextlib.contextmanager
def _quiet():
    """SmolVLA prints "Reducing the number of VLM layers to N ..." while it builds."""
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        yield

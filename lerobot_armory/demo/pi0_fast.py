"""Build a π0-FAST policy directory offline: LeRobot's ``PI0FastConfig`` / ``PI0FastPolicy`` with
random weights and its own pre/post-processors, with stand-ins for both hub tokenizers inside it.

    lerobot-armory-make-demo-policy --kind=pi0_fast --output=out/pi0fast-tiny

π0-FAST decodes actions autoregressively: PaliGemma generates text tokens, the top of the text
vocabulary stands for FAST action tokens (``vocab_size - 1 - fast_skip_tokens - id``), and the
FAST tokenizer turns those back into a chunk (BPE -> DCT coefficients -> inverse DCT). Its
constructor and pre-processor load two tokenizers from the hub, ``google/paligemma-3b-pt-224``
(gated) and ``lerobot/fast-action-tokenizer`` (remote code); both names are config fields, so
this module writes local stand-ins and names them:

- ``DIR/tokenizer``: the stand-in PaliGemma tokenizer (:mod:`.standin_tokenizer`, with ``|``,
  the end-of-action marker, as one token like PaliGemma's); the model's vocabulary is the
  tokenizer's (``pi05_variants`` sizes it so for π0-FAST, as PaliGemma's);
- ``DIR/fast``: a FAST tokenizer trained here in a fraction of a second on random smooth chunks
  of this policy's size, with exactly as many BPE tokens as the text vocabulary, and the processor
  class (:mod:`.processing_action_tokenizer`, loaded with ``trust_remote_code`` as the hub's is).

With ``fast_skip_tokens=0`` every id the model can generate is a FAST token, so a chunk always
decodes (LeRobot pads or cuts the coefficients to ``n_action_steps × action_dim``): a random
model gives random, non-zero chunks. (With LeRobot's 128 skipped ids, or a FAST vocabulary that
does not cover the text vocabulary, most random sequences fail to decode and LeRobot falls back to
all-zero chunks.) ``validate_action_token_prefix`` is off: a random model does not start with
"Action:". Greedy decoding (``temperature=0``) is deterministic; there is no noise argument.

The Gemma size is the registered ``armory_tiny`` (:mod:`lerobot_armory.policies.pi05_variants`),
SigLIP at ``image_resolution`` 32². The server points both tokenizer names (config and the
pre-processor's ``tokenizer_processor`` / ``action_tokenizer_processor`` steps) at ``DIR/tokenizer``
and ``DIR/fast`` wherever the directory has moved (``engine/policy_engine.py``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features, unit_stats, save_policy
from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.policies.layout import FAST_DIR, TOKENIZER_DIR  # where the loader looks for them

SCALE = 10  # FAST's: DCT coefficients × 10, rounded
DECODING_STEPS = 16  # generated tokens per chunk (LeRobot's default is 256)


def make_pi0_fast_policy(cfg: DemoPolicyConfig, cameras: list[str]) -> Path:
    """Build and save the tiny π0-FAST of ``cfg``; returns its directory."""
    import torch
    from transformers import AutoTokenizer

    from lerobot_armory.policies import pi05_variants
    from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer

    inputs, outputs = policy_features("π0-FAST", cfg.chunk_size, cfg.state_dim, cfg.action_dim, cameras, cfg.image_size, max_dim=32)
    try:
        pi05_variants.register()
        from lerobot.policies.pi0_fast.configuration_pi0_fast import PI0FastConfig
        from lerobot.policies.pi0_fast.modeling_pi0_fast import PI0FastPolicy
    except ImportError as exc:
        raise ConfigError("kind", f"π0-FAST needs LeRobot's pi extra (pip install 'lerobot-armory[pi]'): {exc}") from None
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    # "|" is π0-FAST's end-of-action marker, one token in PaliGemma's vocabulary: decoding cuts a
    # sequence there (and stops when every row has emitted it), so a row's chunk is the same
    # batched or alone.
    text = build_standin_tokenizer(out / TOKENIZER_DIR, max_id=pi05_variants.TINY_VOCAB, symbols=("|",))
    vocab = AutoTokenizer.from_pretrained(text).vocab_size
    action_dim = outputs["action"].shape[0]
    fast = build_standin_fast(out / FAST_DIR, vocab, cfg.chunk_size, action_dim, cfg.seed)
    config = PI0FastConfig(
        paligemma_variant=pi05_variants.TINY,
        action_expert_variant=pi05_variants.TINY,  # unused by π0-FAST; validated all the same
        image_resolution=(32, 32),
        tokenizer_max_length=64,
        chunk_size=cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
        text_tokenizer_name=str(text.resolve()),
        action_tokenizer_name=str(fast.resolve()),
        fast_skip_tokens=0,  # every generated id is a FAST token (module docstring)
        max_action_tokens=DECODING_STEPS,
        max_decoding_steps=DECODING_STEPS,
        validate_action_token_prefix=False,
        dtype="float32",
        input_features=inputs,
        output_features=outputs,
        device="cpu",
    )
    torch.manual_seed(cfg.seed)
    policy = PI0FastPolicy(config)
    return save_policy(out, policy, config, unit_stats(inputs, outputs), {"kind": "pi0_fast", "size": "tiny", "random_weights": True, "seed": cfg.seed})


def build_standin_fast(output: Path, vocab_size: int, chunk_size: int, action_dim: int, seed: int = 0) -> Path:
    """Train a FAST tokenizer of exactly ``vocab_size`` BPE tokens on random smooth chunks
    ``(chunk_size, action_dim)`` in [-1, 1] and save it with its processor class in ``output``;
    returns ``output``. Needs no network."""
    import numpy as np
    from scipy.fft import dct
    from tokenizers import Tokenizer, decoders, models, trainers
    from transformers import PreTrainedTokenizerFast

    from lerobot_armory.demo import processing_action_tokenizer

    rng = np.random.default_rng(seed)
    walks = np.cumsum(rng.normal(0.0, 0.1, (2000, chunk_size, action_dim)), axis=1).clip(-1, 1)
    coefficients = np.around(dct(walks, axis=1, norm="ortho") * SCALE).astype(int).reshape(len(walks), -1)
    low, high = int(coefficients.min()), int(coefficients.max())
    # Characters chr(coefficient - low); a plain BPE whose decoder joins the pieces, so every id
    # decodes to coefficients inside the trained range.
    bpe = Tokenizer(models.BPE())
    bpe.decoder = decoders.Fuse()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        min_frequency=1,
        show_progress=False,
        special_tokens=[],
        initial_alphabet=[chr(i) for i in range(high - low + 1)],
        max_token_length=10_000,
    )
    bpe.train_from_iterator(("".join(map(chr, c - low)) for c in coefficients), trainer=trainer)
    if bpe.get_vocab_size() != vocab_size:
        raise ValueError(f"the stand-in FAST tokenizer has {bpe.get_vocab_size()} tokens, not {vocab_size}")
    output.mkdir(parents=True, exist_ok=True)
    PreTrainedTokenizerFast(tokenizer_object=bpe, clean_up_tokenization_spaces=False).save_pretrained(output)
    shutil.copyfile(processing_action_tokenizer.__file__, output / "processing_action_tokenizer.py")
    processor = {
        "processor_class": "UniversalActionProcessor",
        "auto_map": {"AutoProcessor": "processing_action_tokenizer.UniversalActionProcessor"},
        "scale": SCALE, "vocab_size": vocab_size, "min_token": low, "time_horizon": chunk_size, "action_dim": action_dim,
    }  # fmt: skip
    (output / "processor_config.json").write_text(json.dumps(processor, indent=2) + "\n")
    return output

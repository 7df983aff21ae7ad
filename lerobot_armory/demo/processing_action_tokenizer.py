"""A FAST action tokenizer processor, the class the hub's ``lerobot/fast-action-tokenizer`` names.

Self-contained on purpose: :mod:`.pi0_fast` copies this file into ``DIR/fast`` next to the BPE
tokenizer it trains, and LeRobot's π0-FAST loads it from there with
``AutoProcessor.from_pretrained(DIR/fast, trust_remote_code=True)`` (the ``auto_map`` of
``processor_config.json`` names it), as it loads the hub's. Its encoding is FAST's (Pertsch et
al. 2025; LeRobot ships the same class as ``molmoact2/.../action_tokenizer.py``): a chunk's DCT
coefficients, scaled and rounded, written as characters ``chr(coefficient - min_token)`` and
BPE-encoded. π0-FAST decodes with ``bpe_tokenizer``, ``min_token`` and ``scale`` itself.
"""

from typing import ClassVar

import numpy as np
from transformers.processing_utils import ProcessorMixin


class UniversalActionProcessor(ProcessorMixin):
    """FAST: DCT + BPE action tokens (``tokenizer`` is the BPE tokenizer)."""

    attributes: ClassVar[list[str]] = ["tokenizer"]
    tokenizer_class = "AutoTokenizer"

    def __init__(self, tokenizer, scale=10, vocab_size=1024, min_token=0, *, action_dim=None, time_horizon=None):
        self.scale = scale
        self.vocab_size = vocab_size
        self.min_token = min_token
        self.action_dim = action_dim
        self.time_horizon = time_horizon
        super().__init__(tokenizer)
        self.bpe_tokenizer = self.tokenizer

    def __call__(self, action_chunk):
        """``(B, T, D)`` or ``(T, D)`` actions -> one list of token ids per chunk."""
        from scipy.fft import dct

        chunk = np.asarray(action_chunk)
        if chunk.ndim == 2:
            chunk = chunk[None]
        coefficients = np.around(dct(chunk, axis=1, norm="ortho") * self.scale)
        return [
            self.bpe_tokenizer("".join(map(chr, np.maximum(c.flatten() - self.min_token, 0).astype(int))))["input_ids"]
            for c in coefficients
        ]

    def decode(self, tokens, *, time_horizon=None, action_dim=None):
        """Token id lists -> ``(B, T, D)`` actions (a sequence of the wrong length decodes to zeros)."""
        from scipy.fft import idct

        t, d = time_horizon or self.time_horizon, action_dim or self.action_dim
        out = []
        for ids in tokens:
            coefficients = np.array([ord(c) for c in self.bpe_tokenizer.decode(ids)]) + self.min_token
            if coefficients.size != t * d:
                coefficients = np.zeros(t * d)
            out.append(idct(coefficients.reshape(t, d) / self.scale, axis=0, norm="ortho"))
        return np.stack(out)

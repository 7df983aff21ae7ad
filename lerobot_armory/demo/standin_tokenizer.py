"""A local stand-in for a gated VLA tokenizer, stored inside the policy directory.

π0.5's pre-processor tokenizes each robot's prompt with ``google/paligemma-3b-pt-224``, a gated
hub download. For a demo policy with random weights any tokenizer with PaliGemma's conventions
does the same job: a SentencePiece BPE model (byte fallback, so any text encodes; digits split,
so the discretised state "12 255 3" is tokenized as PaliGemma does it) with Gemma's special-token
ids (pad 0, eos 1, bos 2, unk 3) and a ``<bos>`` in front of every prompt. It is trained here,
in about a second, on a small fixed text, and converted to a ``transformers`` ``GemmaTokenizer``
saved as ``tokenizer.json`` (loading it needs neither the network nor ``sentencepiece``).

Every id it emits is below ``vocab_size``, so it fits any embedding table at least that large
(the real PaliGemma vocabulary has 257 152 entries; the tiny variant's has 1024).
"""

from __future__ import annotations

import io
import json
import tempfile
from pathlib import Path

# Text the stand-in is trained on: π0.5's prompt template, the numbers of its discretised state,
# and the words of common robot tasks. Fixed, so a build is reproducible.
_CORPUS = [
    "Task: {task}, State: {state};\nAction: ",
    "pick up the red block and place it in the bin",
    "sort the bricks by colour",
    "reach the moving target",
    "touch the static target",
    "open the drawer and close the drawer",
    "push the button, fold the towel, stack the cups",
    "put the bowl on the plate, wipe the table",
    "insert the peg into the hole",
    "move the arm to the left, to the right, up and down",
]


def build_standin_tokenizer(
    output: str | Path, vocab_size: int = 400, max_id: int | None = None, symbols: tuple[str, ...] = ()
) -> Path:
    """Train and save the stand-in tokenizer in ``output`` (created); returns ``output``.

    Args:
        output: directory to write (``tokenizer.json``, ``tokenizer_config.json``).
        vocab_size: SentencePiece pieces, special tokens and 256 byte-fallback pieces included.
        max_id: if given, every id must be below it (the model's vocabulary size).
        symbols: more strings that are one piece each (as ``"\n"`` is), e.g. π0-FAST's
            end-of-action marker ``"|"``, which PaliGemma's tokenizer has as a token.

    Raises:
        ImportError: ``sentencepiece`` or ``transformers`` is missing (LeRobot's ``pi`` extra).
        ValueError: the tokenizer would emit an id outside ``max_id``.
    """
    import sentencepiece as spm
    from transformers import AutoTokenizer

    lines = []
    for k in range(256):  # the state bins π0.5 writes into its prompt, 0..255
        lines.append(_CORPUS[0].format(task=_CORPUS[1 + k % (len(_CORPUS) - 1)], state=f"{k} {255 - k} {(7 * k) % 256}"))
    lines += _CORPUS[1:] * 8
    model = io.BytesIO()
    spm.SentencePieceTrainer.train(
        sentence_iterator=iter(lines),
        model_writer=model,
        vocab_size=vocab_size,
        model_type="bpe",
        byte_fallback=True,
        split_digits=True,
        character_coverage=1.0,
        pad_id=0, eos_id=1, bos_id=2, unk_id=3,
        pad_piece="<pad>", eos_piece="<eos>", bos_piece="<bos>", unk_piece="<unk>",
        user_defined_symbols=["\n", *symbols],  # π0.5's template has a newline; keep it one token
        add_dummy_prefix=False,
        remove_extra_whitespaces=False,
        normalization_rule_name="identity",
        num_threads=1,  # reproducible
        minloglevel=2,
    )  # fmt: skip
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "tokenizer.model").write_bytes(model.getvalue())
        (Path(tmp) / "tokenizer_config.json").write_text(
            json.dumps({"tokenizer_class": "GemmaTokenizer", "add_bos_token": True, "add_eos_token": False})
        )
        tokenizer = AutoTokenizer.from_pretrained(tmp)  # converted from the SentencePiece model
        tokenizer.save_pretrained(out)
    top = max(tokenizer.get_vocab().values())
    if max_id is not None and top >= max_id:
        raise ValueError(f"the stand-in tokenizer's largest id {top} does not fit a vocabulary of {max_id}")
    return out

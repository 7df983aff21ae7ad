"""Which prompt columns a batch uses, read on the host before the pre-processor moves the prompt.

The engine cuts each batch's prompt to a bucket (``--engine.prompt_buckets``), which needs to know
which token columns any row uses. Read from the device mask, that is a read-back: the host waits for
everything queued before it — with ``--engine.early_vision``, for the vision tower's graph — and the
GPU then idles while the host fits the prompt and copies the inputs in. LeRobot's tokenizer makes
the mask on the host; :class:`HostPromptColumns` reads it there, with a hook before the pipeline's
device step, and binds what it read to the very tensor the device step makes (a hook after it), so
a batch's bucket is chosen from its own mask or, for any other tensor, by the read-back as before.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

DEVICE_STEP = "device_processor"


class HostPromptColumns:
    """Hooks on a LeRobot pre-processor that keep, for the last batch, the prompt columns any row
    uses (``mask.any(dim=0)``, read on the host) and the device mask tensor they belong to.

    Attach only to a pipeline whose every step is one of LeRobot's own known steps (none changes
    the prompt mask after the device step), as the engine does.
    """

    def __init__(self, preprocessor: Any) -> None:
        from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK

        self._key = OBS_LANGUAGE_ATTENTION_MASK
        steps = list(getattr(preprocessor, "steps", []))
        names = [getattr(type(step), "_registry_name", None) for step in steps]
        self._device = names.index(DEVICE_STEP) if DEVICE_STEP in names else None
        self._last = len(steps) - 1
        self._pending: tuple[Any, Tensor] | None = None  # (after the device step: its mask, the columns used)
        self._kept: tuple[Any, Tensor] | None = None  # the same, for the batch the pipeline returned last
        self._used: Tensor | None = None  # read before the device step
        if self._device is not None:
            preprocessor.register_before_step_hook(self._before)
            preprocessor.register_after_step_hook(self._after)

    @property
    def attached(self) -> bool:
        return self._device is not None

    def used(self, masks: Tensor) -> Tensor | None:
        """The columns the rows of ``masks`` use, on the host, if ``masks`` is the mask the
        pipeline returned last; None otherwise (the caller reads it back)."""
        kept = self._kept
        if kept is None or kept[0] is not masks:
            return None
        return kept[1]

    def _mask(self, transition: Any) -> Any:
        from lerobot.lerobot_types import TransitionKey

        observation = transition.get(TransitionKey.OBSERVATION) if isinstance(transition, dict) else None
        return observation.get(self._key) if isinstance(observation, dict) else None

    def _before(self, index: int, transition: Any) -> None:
        if index == 0:  # a new batch: nothing read for it yet
            self._used, self._pending, self._kept = None, None, None
        if index == self._device:
            mask = self._mask(transition)
            ok = isinstance(mask, torch.Tensor) and mask.device.type == "cpu" and mask.dim() == 2
            self._used = mask.any(dim=0) if ok else None

    def _after(self, index: int, transition: Any) -> None:
        if index == self._device and self._used is not None:
            self._pending = (self._mask(transition), self._used)
        if index == self._last and self._pending is not None:
            # Kept only if no step after the device step replaced the mask.
            self._kept = self._pending if self._mask(transition) is self._pending[0] else None

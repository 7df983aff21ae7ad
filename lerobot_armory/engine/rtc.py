"""Real-time chunking (RTC) across the network, one prefix per robot in a batch.

RTC (Black et al., 2025) generates a new chunk with its first actions guided toward what the
robot will execute anyway while the chunk is being computed and sent, so that the switch to the
new chunk does not jump. It needs two numbers per request: ``inference_delay`` (steps the robot
executes before the chunk arrives) and ``prev_chunk_left_over`` (those actions, and the rest of
what it would go on executing). LeRobot 0.6 implements it for local inference only
(``lerobot/policies/rtc/modeling_rtc.py``), with one delay per call. Here the mirror predicts both
for every robot of a batch (:meth:`lerobot_armory.mirror.RobotMirror.prefix_of`) and this module
hands them to the policy:

- :class:`BatchedRTCProcessor` subclasses LeRobot's ``RTCProcessor``: the policy's own sampling
  loop (``euler_integrate``) calls its ``denoise_step`` at every flow step, as it calls LeRobot's.
  Given one :class:`RowPrefixes` it builds a ``(B, T, 1)`` stack of LeRobot's own prefix weights
  (``get_prefix_weights(delay_b, horizon_b, T)``, per row) and applies LeRobot's guidance to the
  whole batch in one pass; given a plain integer delay it is LeRobot's processor, untouched.
  Rows are independent in the denoiser, so row ``b`` equals LeRobot's single-robot RTC with row
  ``b``'s delay and leftover (``tests/engine/test_rtc.py`` checks it, on the guidance step and through a
  whole π0.5 forward pass).
- :func:`enable` installs it on a policy that supports RTC (π0, π0.5, SmolVLA: the policies whose
  ``predict_action_chunk`` forwards ``inference_delay`` / ``prev_chunk_left_over`` to that loop)
  and refuses any other policy with one line.

Leftovers live in the policy's own action space (the output of ``predict_action_chunk``, before
the post-processor un-normalises it), as in LeRobot's ``ActionQueue.get_left_over``.

Note on cost: LeRobot 0.6.1 evaluates the velocity before it marks ``x_t`` as requiring a
gradient, so its guidance's vector-Jacobian product is taken through ``x_t - t·v_t`` with ``v_t``
held fixed (the correction is the weighted error itself), not through the denoiser. We keep those
semantics (equality with LeRobot is the contract); the engine freezes the policy's parameters, so
no autograd graph is recorded through the model either, and RTC's extra cost is small. It is
profiled into ``d_infer(b)`` all the same (``PolicyEngine.profile`` runs guided batches).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lerobot_armory.engine.options import RTCOptions
from lerobot_armory.errors import ConfigError
from lerobot_armory.acceleration.rtc_guidance import guidance_weight


@dataclass(frozen=True)
class Prefix:
    """What one robot will execute from its chunk's first index on, as the mirror predicts it.

    Attributes:
        leftover: ``(L, A)`` actions in the policy's action space: the robot's actions at indices
            ``i_start .. i_start + L - 1`` if the new chunk never came (L >= 1).
        inference_delay: steps executed before the new chunk arrives (its first action executed
            is ``inference_delay``).
    """

    leftover: np.ndarray
    inference_delay: int


@dataclass(frozen=True)
class RowPrefixes:
    """Per-row RTC parameters for one batch, passed where LeRobot passes ``inference_delay``
    (LeRobot forwards it verbatim from ``predict_action_chunk`` to the processor).

    ``horizons[b]`` is row b's execution horizon already capped by its leftover's length
    (0: no leftover, no guidance for that row); ``lengths[b]`` that length.
    """

    delays: tuple[int, ...]
    horizons: tuple[int, ...]
    lengths: tuple[int, ...]


def unsupported_reason(policy: Any) -> str | None:
    """Why ``--rtc.enabled`` cannot serve this policy (None: it can)."""
    supports = getattr(policy, "supports_rtc", None)
    name = getattr(getattr(policy, "config", None), "type", type(policy).__name__)
    if getattr(policy, "accepts_rtc_rows", False):
        return None
    if not callable(supports) or not supports():
        return f"{name} policies do not support real-time chunking (LeRobot's RTC: π0, π0.5, SmolVLA)"
    if not callable(getattr(policy, "init_rtc_processor", None)) or not hasattr(getattr(policy, "model", None), "rtc_processor"):
        return f"{name} implements RTC in its own way; batched per-robot RTC supports π0, π0.5 and SmolVLA"
    return None


def enable(policy: Any, options: RTCOptions) -> Any:
    """Turn RTC on for ``policy`` with a :class:`BatchedRTCProcessor`; returns the processor.

    Raises:
        ConfigError: the policy does not support RTC (one line).
    """
    options.validate()
    why = unsupported_reason(policy)
    if why is not None:
        raise ConfigError("rtc.enabled", why)
    if getattr(policy, "accepts_rtc_rows", False):
        return NativeRows(policy)
    policy.config.rtc_config = options.lerobot_config()
    processor = processor_class()(policy.config.rtc_config)
    policy.rtc_processor = processor
    policy.model.rtc_processor = processor
    return processor


class NativeRows:
    """RTC done by the policy itself: a policy with ``accepts_rtc_rows = True`` (``armory_planner``)
    takes :class:`RowPrefixes` and the stacked leftover in ``predict_action_chunk`` and counts the
    guided calls in ``rtc_calls``."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    @property
    def calls(self) -> int:
        return int(getattr(self.policy, "rtc_calls", 0))


@functools.cache
def processor_class() -> type:
    """:class:`BatchedRTCProcessor` (built on first use: LeRobot and torch load lazily)."""
    import torch
    from lerobot.policies.rtc.modeling_rtc import RTCProcessor

    class BatchedRTCProcessor(RTCProcessor):
        """LeRobot's ``RTCProcessor`` that also takes one delay and horizon per batch row."""

        calls = 0  # guided denoising steps taken with per-row prefixes (a policy that never calls us is refused)

        def denoise_step(
            self,
            x_t: torch.Tensor,
            prev_chunk_left_over: torch.Tensor | None,
            inference_delay: Any,
            time: float,
            original_denoise_step_partial: Any,
            execution_horizon: int | None = None,
        ) -> torch.Tensor:
            if not isinstance(inference_delay, RowPrefixes) or prev_chunk_left_over is None:
                return super().denoise_step(
                    x_t, prev_chunk_left_over, inference_delay, time, original_denoise_step_partial, execution_horizon
                )
            self.calls += 1
            rows, length, dim = x_t.shape
            if len(inference_delay.delays) != rows or prev_chunk_left_over.shape[0] != rows:
                raise ValueError(f"{len(inference_delay.delays)} prefixes for a batch of {rows}")
            weights = row_weights(self, inference_delay, length).to(x_t.device)
            leftover = pad_leftover(prev_chunk_left_over, length, dim)
            # From here on LeRobot's guidance, verbatim but for the (B, T, 1) weights.
            x_t = x_t.clone().detach()
            with torch.enable_grad():
                v_t = original_denoise_step_partial(x_t)
                x_t.requires_grad_(True)
                x1_t = x_t - time * v_t
                err = (leftover - x1_t) * weights
                correction = torch.autograd.grad(x1_t, x_t, err.clone().detach(), retain_graph=False)[0]
            return v_t - guidance_weight(time, self.rtc_config.max_guidance_weight) * correction

    return BatchedRTCProcessor


def row_weights(processor: Any, prefixes: RowPrefixes, length: int) -> Any:
    """``(B, length, 1)`` float32 guidance weights: row b is LeRobot's own
    ``get_prefix_weights(delay_b, horizon_b, length)`` (a horizon of 0 gives an all-zero row)."""
    import torch

    return torch.stack(
        [
            processor.get_prefix_weights(d, h, length) if h > 0 else torch.zeros(length)
            for d, h in zip(prefixes.delays, prefixes.horizons, strict=True)
        ]
    )[:, :, None]


def pad_leftover(leftover: Any, length: int, dim: int) -> Any:
    """``leftover`` ``(B, L, D')`` zero-padded to ``(B, length, dim)`` (LeRobot pads it so)."""
    import torch

    out = torch.zeros(leftover.shape[0], length, dim, device=leftover.device)
    out[:, : leftover.shape[1], : leftover.shape[2]] = leftover
    return out


def guidance_kwargs(
    prefixes: Sequence[Prefix | None], chunk_size: int, horizon: int, device: Any, delay_margin: int = 0
) -> dict[str, Any]:
    """The ``predict_action_chunk`` keyword arguments that guide each row by its own prefix
    (each delay plus ``delay_margin``).

    Rows without a prefix (a robot's first chunk) get no guidance; a batch without any gets
    none at all (LeRobot's unguided path).
    """
    import torch

    if all(p is None for p in prefixes):
        return {}
    dim = max(p.leftover.shape[1] for p in prefixes if p is not None)
    stacked = np.zeros((len(prefixes), chunk_size, dim), np.float32)
    delays, horizons, lengths = [], [], []
    for b, p in enumerate(prefixes):
        n = 0 if p is None else min(len(p.leftover), chunk_size)
        if p is not None:
            stacked[b, :n, : p.leftover.shape[1]] = p.leftover[:n]
        # LeRobot caps the horizon by the leftover's length: nothing to merge beyond it.
        horizons.append(min(horizon, n))
        delays.append(0 if p is None else max(0, int(p.inference_delay) + delay_margin))
        lengths.append(n)
    leftover = torch.from_numpy(stacked).to(device)
    return {"inference_delay": RowPrefixes(tuple(delays), tuple(horizons), tuple(lengths)), "prev_chunk_left_over": leftover}

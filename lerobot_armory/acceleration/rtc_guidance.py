"""RTC's guidance weight, shared by LeRobot's sampling loop (``engine/rtc.py``'s batched processor)
and the static sampler (``pi05_static.py``), so the two cannot drift apart."""

from __future__ import annotations

from typing import Any


def guidance_weight(time: float, max_weight: float) -> Any:
    """LeRobot's RTC guidance weight at flow time ``time`` (1: noise, 0: actions), clamped to
    ``max_weight``: a 0-dim float32 tensor computed exactly as ``RTCProcessor.denoise_step`` does."""
    import torch

    tau = torch.as_tensor(1 - time)
    max_w = torch.as_tensor(max_weight)
    inv_r2 = ((1 - tau) ** 2 + tau**2) / ((1 - tau) ** 2)
    c = torch.nan_to_num((1 - tau) / tau, posinf=max_w)
    return torch.minimum(torch.nan_to_num(c * inv_r2, posinf=max_w), max_w)

"""The ``armory_planner`` policy: batched, tensor-only target finding and waypoint planning."""

from __future__ import annotations

from collections import deque

import torch
import torch.nn.functional as F
from torch import Tensor

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_armory.policies.armory_planner.configuration_armory_planner import ArmoryPlannerConfig


class ArmoryPlannerPolicy(PreTrainedPolicy):
    """See :class:`ArmoryPlannerConfig`. Everything is batched tensor code, so a batch of robots
    is one call, as for a learned policy."""

    config_class = ArmoryPlannerConfig
    name = "armory_planner"
    # Real-time chunking, the planner's way: it takes one delay per row (the server's
    # ``RowPrefixes``) and blends the leftover into its fresh plan as RTC's guidance would.
    accepts_rtc_rows = True
    rtc_calls = 0

    def supports_rtc(self) -> bool:
        return True

    def __init__(self, config: ArmoryPlannerConfig, dataset_stats: dict | None = None) -> None:
        super().__init__(config)
        self.config = config
        # Step k of a chunk may move k+1 speed-steps from the effector (kept as a buffer so the
        # policy saves and loads like any LeRobot policy).
        steps = torch.arange(1, config.chunk_size + 1, dtype=torch.float32) * (config.max_speed / config.fps)
        self.register_buffer("reach", steps)
        self._queue: deque[Tensor] = deque()

    def get_optim_params(self) -> dict:
        return {}

    def reset(self) -> None:
        self._queue.clear()

    def locate_target(self, image: Tensor) -> Tensor:
        """Centroid of the red pixels of ``(B, 3, H, W)`` images in [0, 1], in workspace units.

        Images without a red pixel give the image centre (the planner then stays put)."""
        r, g, b = image[:, 0], image[:, 1], image[:, 2]
        mask = ((r > 0.6) & (g < 0.4) & (b < 0.4)).float()
        _, h, w = mask.shape
        xs = (torch.arange(w, device=image.device, dtype=torch.float32) + 0.5) / w * 2 - 1
        ys = 1 - (torch.arange(h, device=image.device, dtype=torch.float32) + 0.5) / h * 2
        total = mask.sum(dim=(1, 2)).clamp_min(1.0)
        x = (mask.sum(dim=1) * xs).sum(dim=1) / total
        y = (mask.sum(dim=2) * ys).sum(dim=1) / total
        return torch.stack([x, y], dim=1)

    @torch.no_grad()
    def predict_action_chunk(
        self, batch: dict[str, Tensor], inference_delay: object = None, prev_chunk_left_over: Tensor | None = None, **kwargs
    ) -> Tensor:
        """``(B, H, 2)`` waypoints from the effector straight to the target, then on it.

        With a leftover (RTC's contract: ``prev_chunk_left_over`` ``(B, T, 2)`` and
        ``inference_delay``, one int for every row or per-row ``delays`` / ``horizons``), row b
        is blended as RTC's LINEAR schedule weighs its guidance: the first ``d_b`` actions are
        the leftover's (the robot executes them anyway while the chunk is on its way), the
        weight then falls linearly to 0 at the row's execution horizon, and from there on the
        plan is the fresh one (closed loop: from the effector observed, to the target seen).
        """
        effector = batch["observation.state"][:, :2].float()
        target = self.locate_target(batch[self.config.camera].float())
        delta = target - effector
        dist = delta.norm(dim=1, keepdim=True)  # (B, 1)
        direction = delta / dist.clamp_min(1e-6)
        travel = torch.minimum(self.reach[None, :], dist)  # (B, H)
        plan = effector[:, None, :] + direction[:, None, :] * travel[:, :, None]
        if prev_chunk_left_over is None or inference_delay is None:
            return plan
        rows, horizon = plan.shape[:2]
        given = prev_chunk_left_over if prev_chunk_left_over.ndim == 3 else prev_chunk_left_over[None].expand(rows, -1, -1)
        left = torch.zeros(rows, horizon, 2, device=plan.device)
        n = min(given.shape[1], horizon)
        left[:, :n] = given[:, :n, :2].to(left)
        delays = getattr(inference_delay, "delays", None) or [int(inference_delay)] * rows  # type: ignore[call-overload]
        ends = getattr(inference_delay, "horizons", None) or [n] * rows
        k = torch.arange(horizon, device=plan.device, dtype=torch.float32)
        d = torch.tensor([min(x, e) for x, e in zip(delays, ends, strict=True)], device=plan.device, dtype=torch.float32)[:, None]
        e = torch.tensor(list(ends), device=plan.device, dtype=torch.float32)[:, None]
        weight = torch.where(k[None, :] < d, 1.0, ((e - k[None, :]) / (e - d + 1)).clamp(0.0, 1.0))  # (B, H)
        self.rtc_calls += 1
        return weight[:, :, None] * left + (1 - weight[:, :, None]) * plan

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        if not self._queue:
            chunk = self.predict_action_chunk(batch)[:, : self.config.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Imitation loss of the planner's chunk against demonstrated actions (L2). There are no
        weights to fit; the loss tells how far a demonstration is from the planner."""
        plan = self.predict_action_chunk(batch)
        loss = F.mse_loss(plan, batch["action"].float())
        return loss, {"l2": float(loss)}

"""Lookahead (docs/spec.md §3): roll the mirror forward for candidate schedules, dispatch the best.

A schedule is ``L`` batches (``L`` = depth). Its score is ``Σ_ℓ R_ℓ / d_infer(|B_ℓ|)`` with
``R_ℓ`` the weighted executed robot time the batch *adds* inside a window of ``window_s``
seconds from the decision time (the window's executed time with its chunks minus without them):
robot-seconds gained per GPU-second. (The literal reading of docs/spec.md §3, the whole fleet's executed
time after the batch, favours tiny batches; the study measured it and it is not offered.)

How the search stays cheap. Robots do not interact except through the batch they share, so the
gain of adding robot j to a batch of size ``s`` depends only on j and ``s`` (through
``d_infer(s)``). For one epoch the best batch of size ``s`` is therefore exactly the ``s``
robots with the largest gain at size ``s``; the search tries every size ``1..b`` and so picks
its own batch size (it never over-batches just because the cap allows it). Deeper epochs
branch on those ``b`` candidates per level (candidate pruning) and stop expanding when the time
budget is spent; the first epoch is always evaluated in full, so a decision never depends on
machine speed at depth 1.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror, WindowView, request_is_useful
from lerobot_armory.transition import TickChunk, advance, observed_tick
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig

class _Robot:
    """One robot inside a rollout: its window view plus the chunks a schedule adds."""

    __slots__ = ("view", "mirror", "weight_per_tick", "h", "h_min", "one_way", "base", "last_served", "_deadline")

    def __init__(self, view: WindowView) -> None:
        self.view = view
        self.mirror = view.mirror
        spec = view.mirror.spec
        self.weight_per_tick = spec.weight / spec.fps
        self.h = spec.h_max
        self.h_min = spec.h_min
        self.one_way = view.mirror.estimator.one_way_s
        self.base = view.executed()
        self.last_served = view.mirror.last_served_index
        self._deadline: float | None = None

    @property
    def deadline(self) -> float:
        """EDF deadline, computed only when a tie needs it."""
        if self._deadline is None:
            self._deadline = self.mirror.deadline()
        return self._deadline

    def obs_index_at(self, t: float, extra: Sequence[TickChunk]) -> int | None:
        """Index of the latest observation the server will hold at ``t`` (None: none yet)."""
        mirror = self.mirror
        if t <= self.view.now:
            return mirror.obs_index
        tick = observed_tick(t, self.view.origin_time, mirror.spec.fps, self.one_way)
        if tick < 0 or mirror.obs_index is None:
            return mirror.obs_index
        chunks = sorted([*self.view.chunks, *extra]) if extra else self.view.chunks
        return max(mirror.obs_index, advance(self.view.index, chunks, tick))

    def useful_at(self, obs_index: int | None, last_served: int | None) -> bool:
        """docs/spec.md §3 usefulness for a predicted observation (the mirror's rule)."""
        return request_is_useful(obs_index, last_served, self.h_min)


class LookaheadScheduler(Scheduler):
    """Lookahead over ``depth`` epochs with per-robot weights (from each robot's spec)."""

    # Across policies, by deadline (arbiter.py): its score is robot time gained per device-second,
    # and a cheap policy's batches always score high, so arbitrating by score gave an ACT beside a
    # π0.5 the device while the π0.5 robots starved (docs/results/multi_policy).
    arbitration = "deadline"

    def __init__(
        self,
        profile: LatencyProfile,
        max_batch_size: int,
        depth: int = 1,
        window_s: float = 1.0,
        time_budget_ms: float = 5.0,
    ) -> None:
        super().__init__(profile, max_batch_size)
        if depth < 1:
            raise ConfigError("scheduler.depth", f"must be >= 1, got {depth}")
        if not window_s > 0:
            raise ConfigError("scheduler.window_s", f"must be > 0, got {window_s}")
        if not time_budget_ms > 0:
            raise ConfigError("scheduler.time_budget_ms", f"must be > 0, got {time_budget_ms}")
        self.depth = depth
        self.window_s = window_s
        self.time_budget_s = time_budget_ms / 1000.0

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        pool = [_Robot(r.window_view(now, self.window_s)) for r in robots if r.obs_index is not None]
        self._give_up_at = time.perf_counter() + self.time_budget_s
        best_score, best_first = -math.inf, None
        for first, score in self._expand(pool, now, {}, {}, 0.0, 1):
            if score > best_score:
                best_score, best_first = score, first
        # Robot-seconds gained per device-second: comparable across policies of different speeds.
        self.last_score = best_score if best_first is not None else None
        return [] if best_first is None else [r.mirror for r in best_first]

    def _candidates(
        self, pool: Sequence[_Robot], t: float, extras: dict[int, list[TickChunk]], served: dict[int, int | None]
    ) -> list[tuple[list[_Robot], float, dict[int, TickChunk]]]:
        """Best batch of every size 1..b at epoch time ``t``: (robots, summed gain, new chunks)."""
        d = self.d_infer
        gains: list[tuple[int, _Robot, list[float], list[TickChunk]]] = []
        for k, robot in enumerate(pool):
            extra = extras.get(k, ())
            last = served.get(k, robot.last_served)
            obs = robot.obs_index_at(t, extra)
            if not robot.useful_at(obs, last):
                continue
            before = robot.view.executed(extra) if extra else robot.base
            memo: dict[int, tuple[float, TickChunk]] = {}
            per_size, chunk_by_size = [], []
            for s in range(1, self.max_batch_size + 1):
                tick = robot.view.arrival_tick(t + d[s - 1] + robot.one_way)
                if tick not in memo:
                    chunk = (obs, obs + robot.h, tick)
                    gain = 0 if tick >= robot.view.window_ticks else robot.view.executed([*extra, chunk]) - before
                    memo[tick] = (gain * robot.weight_per_tick, chunk)
                gain_s, chunk_s = memo[tick]
                per_size.append(gain_s)
                chunk_by_size.append(chunk_s)
            gains.append((k, robot, per_size, chunk_by_size))
        out = []
        for s in range(1, min(self.max_batch_size, len(gains)) + 1):
            # Largest gain first; ties go to the earliest deadline, then registration order.
            ranked = sorted(gains, key=lambda g: (-g[2][s - 1], g[1].deadline, g[0]))[:s]
            out.append(([g[1] for g in ranked], sum(g[2][s - 1] for g in ranked), {g[0]: g[3][s - 1] for g in ranked}))
        return out

    def _expand(
        self,
        pool: Sequence[_Robot],
        t: float,
        extras: dict[int, list[TickChunk]],
        served: dict[int, int | None],
        score: float,
        level: int,
    ):
        """Yield ``(first batch, schedule score)`` for every schedule explored from epoch ``level``."""
        for batch, gain, chunks in self._candidates(pool, t, extras, served):
            d = self.d_infer[len(batch) - 1]
            total = score + gain / d
            deeper = level < self.depth and time.perf_counter() < self._give_up_at
            if not deeper:
                yield batch, total
                continue
            next_extras = dict(extras)
            next_served = dict(served)
            for k, chunk in chunks.items():
                next_extras[k] = [*extras.get(k, ()), chunk]
                next_served[k] = chunk[0]
            explored = False
            for _, sub_score in self._expand(pool, t + d, next_extras, next_served, total, level + 1):
                explored = True
                yield batch, sub_score
            if not explored:  # nobody is useful at the next epoch: the schedule ends here
                yield batch, total


@SchedulerConfig.register_subclass("lookahead")
@dataclass
class LookaheadConfig(SchedulerConfig):
    """Lookahead knobs.

    Attributes:
        depth: epochs L searched per decision.
        window_s: reward window from the decision time, seconds.
        time_budget_ms: deeper epochs stop expanding after this much search time.
    """

    depth: int = 1
    window_s: float = 1.0
    time_budget_ms: float = 5.0

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return LookaheadScheduler(profile, max_batch_size, self.depth, self.window_s, self.time_budget_ms)

    def label(self) -> str:
        return (f"lookahead L={self.depth}" if self.depth != 1 else "lookahead") + self.timing_label()

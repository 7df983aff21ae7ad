"""Offline optimum for small fleets: the best work-conserving schedule of a deterministic episode.

What is optimised. A deterministic :class:`Episode` fixes everything a schedule cannot change:
the robots (docs/spec.md §1 specs, weights included), the latency profile ``d_infer(b)``, a jitter-free
network (every one-way delay is exactly ``net_s``, so the mirror is exact), each robot's tick
phase (all 0 by default: a synchronous cold start with empty queues), a horizon ``T`` and an
optional warm-up (decisions before ``warmup_s`` are EDF's for everybody and only later ticks are
scored, to start the scored window from a fleet in its running rhythm). A
*schedule* is the sequence of batches dispatched at the instants the device becomes free, under
the same rules every online scheduler obeys (docs/spec.md §3): a batch is a non-empty set of at most
``b`` distinct *useful* robots, and the device is **work-conserving**, i.e. it dispatches
whenever some robot is useful and otherwise waits for the next observation. The optimum is the
schedule that maximises the docs/spec.md §2 reward summed over the episode, i.e. the weighted executed
robot time ``Σ_j w_j · (steps executed before T) / fps_j``. Schedules that idle on purpose while
a robot is useful are *not* in the search space (no online scheduler may do that either), so
"optimal" here means optimal among work-conserving schedules.

How. Depth-first branch-and-bound over batch choices (every subset of the useful robots of size
``1..b``, so the batch size is chosen too), with

- the transition of :func:`lerobot_armory.transition.advance` (never re-implemented): each robot's
  state is its chunk queue on its own tick grid, relative to its latest observation;
- a canonical state (the queue reduced to "which indices are covered from which tick on",
  indices and ticks relative to the robot) so equivalent states meet in one memo entry, and
  symmetry reduction: robots with the same spec and the same state are interchangeable, both in
  the memo key and when enumerating batches;
- an admissible bound: a robot executes what its current queue covers until the first tick a new
  chunk could possibly arrive (a batch of one dispatched now), and at best every tick after that;
- an incumbent: the best value any online scheduler reached on the same episode (children are
  explored best-bound first, so better schedules tighten the cut quickly).

A result is **exact** when the search finishes (the root's value is exact, or its upper bound
does not exceed the incumbent, which proves the incumbent optimal). When the node budget runs
out first, every unexpanded node contributes its admissible bound, so the root value is still a
proven **upper bound**, and the best schedule found is a lower bound; :class:`OptimumResult`
says which of the two happened.

How long a horizon can be solved exactly depends on the load: an underloaded fleet's optimum
meets the bound (nobody starves after the first chunks) and 5 s is solved in well under a
second; an overloaded one (all-fast libero fleets from N = 3) is exponential in the horizon and
only ~1-2.5 s finish in tens of seconds. ``armory_research.frontier`` therefore tries 5 s
and falls back to the longest shorter horizon it can solve, and reports which; at 5 s it brackets
the optimum with :mod:`armory_research.bound`'s Lagrangian upper bound, which holds for any
schedule and is much tighter than this search's own bound when the fleet is overloaded.

Every value the search reports can be checked: :func:`play` drives the real
:class:`~lerobot_armory.mirror.RobotMirror` / :class:`~lerobot_armory.mirror.RobotTimeline`
objects with any scheduler on the same episode, and :class:`ReplayScheduler` replays the
optimal plan through it (the test suite checks the two agree to the last step).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

from lerobot_armory.dispatch import Dispatcher
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.delay import DelayEstimator
from lerobot_armory.mirror import RobotMirror, RobotTimeline
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.transition import Chunk, advance, tick_of
from lerobot_armory.schedulers.base import Scheduler
from lerobot_armory.schedulers.edf import EarliestDeadlineScheduler
from lerobot_armory.sim.presets import fleet_specs, get_preset

# Same tolerance as the mirror's tick mapping: an observation captured exactly ``net_s`` before
# a decision has reached the server.
_EPS = 1e-9

# A wait "until the next observation lands" asks the driver to wake at this much later at the
# latest; every driver wakes at the next observation arrival first.
_FAR_S = 3600.0

# ``since`` value of a robot whose latest observation may be served (never served, or at least
# max(1, h_min) steps executed since its last served observation).
FREE = -1


# --------------------------------------------------------------------------------------------
# The deterministic episode


@dataclass(frozen=True)
class Episode:
    """A deterministic fleet episode that every scheduler and the optimum play identically.

    Attributes:
        specs: the robots, in registration order (weights are part of the objective).
        d_infer_s: ``d_infer(b)`` in seconds for ``b = 1..max batch size``.
        horizon_s: the episode covers ticks strictly before this time.
        net_s: every one-way delay (uplink and downlink), seconds; no jitter.
        phases_s: time of each robot's tick 0 (default: all 0, a synchronous start).
        warmup_s: decisions before this time are EDF's, for every schedule alike, and only ticks
            from this time on are scored: the scored window ``[warmup_s, horizon_s)`` then starts
            from a fleet already in its running rhythm instead of the cold start (0: score from
            the cold start).
    """

    specs: tuple[RobotSpec, ...]
    d_infer_s: tuple[float, ...]
    horizon_s: float
    net_s: float
    phases_s: tuple[float, ...] = ()
    warmup_s: float = 0.0

    def __post_init__(self) -> None:
        if not self.specs:
            raise ConfigError("robots", "the fleet is empty")
        if len({s.robot_id for s in self.specs}) != len(self.specs):
            raise ConfigError("robots", "robot ids must be unique")
        if not self.d_infer_s or any(not d > 0 for d in self.d_infer_s):
            raise ConfigError("latency_profile", "d_infer must be positive for every batch size")
        if not (math.isfinite(self.horizon_s) and self.horizon_s > 0):
            raise ConfigError("horizon_s", f"must be > 0, got {self.horizon_s}")
        if not (math.isfinite(self.warmup_s) and 0 <= self.warmup_s < self.horizon_s):
            raise ConfigError("warmup_s", f"must be in [0, horizon_s), got {self.warmup_s}")
        if not (math.isfinite(self.net_s) and self.net_s >= 0):
            raise ConfigError("net_median_ms", f"must be >= 0, got {self.net_s * 1000}")
        if not self.phases_s:
            object.__setattr__(self, "phases_s", tuple(0.0 for _ in self.specs))
        if len(self.phases_s) != len(self.specs):
            raise ConfigError("phases_s", "needs one phase per robot")
        for s, p in zip(self.specs, self.phases_s, strict=True):
            if not 0 <= p < 1.0 / s.fps:
                raise ConfigError("phases_s", f"phase of {s.robot_id} must be in [0, 1/fps), got {p}")

    @property
    def max_batch_size(self) -> int:
        """Batch cap ``b``."""
        return len(self.d_infer_s)

    def n_ticks(self, j: int) -> int:
        """Ticks of robot ``j`` that happen before the horizon."""
        return max(0, math.ceil((self.horizon_s - self.phases_s[j]) * self.specs[j].fps - _EPS))

    def warm_tick(self, j: int) -> int:
        """First tick of robot ``j`` that is scored (the first at or after ``warmup_s``)."""
        return max(0, math.ceil((self.warmup_s - self.phases_s[j]) * self.specs[j].fps - _EPS))

    def obs_tick(self, j: int, t: float) -> int:
        """Tick whose observation is the latest one the server holds at ``t`` (-1: none yet)."""
        return math.floor((t - self.net_s - self.phases_s[j]) * self.specs[j].fps + _EPS)

    def obs_arrival(self, j: int, k: int) -> float:
        """Server time at which the observation of tick ``k`` of robot ``j`` arrives."""
        return self.phases_s[j] + k / self.specs[j].fps + self.net_s

    def arrival_tick(self, j: int, t_done: float) -> int:
        """First tick of robot ``j`` that can use a chunk whose inference finishes at ``t_done``."""
        return tick_of(t_done + self.net_s, self.phases_s[j], self.specs[j].fps)

    def next_observation(self, t: float) -> float:
        """The first observation arrival of any robot strictly after ``t``."""
        return min(self.obs_arrival(j, self.obs_tick(j, t) + 1) for j in range(len(self.specs)))

    def max_weighted_s(self) -> float:
        """Weighted executed time of the scored window if no robot ever starved."""
        return sum(s.weight * (self.n_ticks(j) - self.warm_tick(j)) / s.fps for j, s in enumerate(self.specs))


def episode_for(
    preset: str,
    mix: str,
    robots: int,
    horizon_s: float,
    fast_weight: float = 1.0,
    latency_profile: str | LatencyProfile | None = None,
    max_batch_size: int | None = None,
    net_median_ms: float | None = None,
    warmup_s: float = 0.0,
) -> Episode:
    """The deterministic episode of a preset fleet (docs/spec.md §5 timing, σ = 0, synchronous start).

    The network delay is the preset's median without jitter; the batch cap and latency profile
    default to the preset's. ``horizon_s`` is the scored length: the episode ends at
    ``warmup_s + horizon_s``.
    """
    p = get_preset(preset)
    profile = latency_profile if isinstance(latency_profile, LatencyProfile) else load_profile(latency_profile or p.latency_profile)
    cap = p.default_batch_cap(mix) if max_batch_size is None else max_batch_size
    if cap < 1:
        raise ConfigError("max_batch_size", f"must be >= 1, got {cap}")
    median = p.net_median_ms if net_median_ms is None else net_median_ms
    return Episode(
        tuple(fleet_specs(p, mix, robots, fast_weight)),
        tuple(profile.table_s(cap)),
        warmup_s + horizon_s,
        median / 1000.0,
        warmup_s=warmup_s,
    )


# --------------------------------------------------------------------------------------------
# Playing a scheduler on an episode (the real mirror objects)


@dataclass
class EpisodeResult:
    """What one schedule achieved on an episode.

    Attributes:
        executed_steps / ticks: per robot, steps executed and ticks in the scored window.
        weighted_executed_s: docs/spec.md §2 reward summed over the scored window.
        batches: robot indices of every dispatched batch, in order (warm-up included).
        warmup_decisions: how many of ``batches`` were the warm-up's (EDF's).
        warmup_weighted_s: weighted executed time before the scored window (the same for every
            schedule of the episode).
    """

    episode: Episode
    executed_steps: list[int]
    ticks: list[int]
    weighted_executed_s: float
    batches: list[tuple[int, ...]] = field(default_factory=list)
    warmup_decisions: int = 0
    warmup_weighted_s: float = 0.0

    def starvation_pct(self, j: int) -> float:
        """Starved ticks of robot ``j`` in % of its ticks."""
        return 100.0 * (self.ticks[j] - self.executed_steps[j]) / self.ticks[j] if self.ticks[j] else 0.0

    def tier_starvation_pct(self, tier: str) -> float:
        """Mean starvation of the robots of ``tier`` (NaN if none)."""
        rows = [self.starvation_pct(j) for j, s in enumerate(self.episode.specs) if s.tier == tier]
        return sum(rows) / len(rows) if rows else float("nan")


def play(episode: Episode, scheduler: Scheduler, tell_end: bool = False) -> EpisodeResult:
    """Run ``scheduler`` on ``episode`` with the real mirror, dispatch step and ground-truth
    timeline classes.

    ``tell_end`` tells the scheduler what the finite-horizon optimum knows, that nothing after
    the end counts: a scheduler that scores a window (``window_s``: Lookahead, Rollout) gets it
    clipped at the episode's end before every decision, and its own window back afterwards. RR
    and EDF do not look ahead. Off by default, as live (the product has no episode end).

    This is the simulator's event loop (docs/spec.md §3 work conservation, latest observation per robot,
    chunk ``(î_j, h_max, t_done + d_action)``) without randomness: delays are exact, so the
    mirror's delay estimate is exact from the start (one registration exchange) and needs no
    execution reports. ``FleetSimulator`` with ``net_sigma = 0`` and the same phases gives the
    same executed steps (checked in the tests). Decisions before ``episode.warmup_s`` are EDF's.
    """
    ep = episode
    n = len(ep.specs)
    m = ep.net_s
    if scheduler.max_batch_size != ep.max_batch_size:
        raise ConfigError("max_batch_size", f"scheduler cap {scheduler.max_batch_size} != episode cap {ep.max_batch_size}")
    window = getattr(scheduler, "window_s", None) if tell_end else None
    warm, main = Dispatcher(_ColdEdf(ep)), Dispatcher(scheduler)
    truth = [RobotTimeline(s.fps, ep.phases_s[j]) for j, s in enumerate(ep.specs)]
    mirrors = []
    for s in ep.specs:
        est = DelayEstimator()
        est.add_exchange(-1.0, -1.0 + m, -1.0 + m, -1.0 + 2 * m)  # offset 0, one-way exactly m
        mirrors.append(RobotMirror(s, est))
    position = {s.robot_id: j for j, s in enumerate(ep.specs)}
    warm_ticks = [ep.warm_tick(j) for j in range(n)]
    warm_index: list[int | None] = [None] * n

    def run_truth(j: int, k: int) -> None:
        # Ticks before the scored window only depend on warm-up decisions: note the index there.
        if warm_index[j] is None and k >= warm_ticks[j]:
            truth[j].run_to(warm_ticks[j])
            warm_index[j] = truth[j].index
        truth[j].run_to(k)

    fed = [-1] * n
    batches: list[tuple[int, ...]] = []
    warmup_decisions = 0
    t = 0.0
    try:
        while t < ep.horizon_s:
            for j, s in enumerate(ep.specs):
                k = ep.obs_tick(j, t)
                if k > fed[j]:
                    run_truth(j, k)
                    fed[j] = k
                    capture = ep.phases_s[j] + k / s.fps
                    mirrors[j].on_observation(truth[j].index, capture, ep.obs_arrival(j, k))
            dispatcher = warm if t < ep.warmup_s else main
            if window is not None:
                scheduler.window_s = min(window, max(1e-3, ep.horizon_s - t))  # type: ignore[attr-defined]
            plan = dispatcher.plan(mirrors, t)
            if plan is None:
                t = ep.next_observation(t)
                continue
            if plan.wait_until is not None:  # dispatch timing: wait (an idle action)
                batches.append(())
                t = min(plan.wait_until, ep.next_observation(t))
                continue
            t_done = t + ep.d_infer_s[plan.size - 1]
            dispatcher.complete(plan, t_done)
            for req in plan.requests:
                c = req.chunk
                truth[position[req.robot_id]].add_chunk(Chunk(c.chunk_id, c.i_start, c.h, t_done + m))
            batches.append(tuple(position[r] for r in plan.robot_ids))
            warmup_decisions += dispatcher is warm
            t = t_done
    finally:
        if window is not None:
            scheduler.window_s = window  # type: ignore[attr-defined]
    ticks = [ep.n_ticks(j) for j in range(n)]
    for j in range(n):
        run_truth(j, ticks[j])
    start = [w if w is not None else 0 for w in warm_index]
    executed = [tl.index - start[j] for j, tl in enumerate(truth)]
    value = sum(s.weight * executed[j] / s.fps for j, s in enumerate(ep.specs))
    before = sum(s.weight * start[j] / s.fps for j, s in enumerate(ep.specs))
    scored = [ticks[j] - warm_ticks[j] for j in range(n)]
    return EpisodeResult(ep, executed, scored, value, batches, warmup_decisions, before)


def _ColdEdf(ep: Episode) -> Scheduler:  # noqa: N802 - reads like the class it builds
    """EDF with the episode's batch cap (the warm-up policy; also a cheap incumbent)."""
    return EarliestDeadlineScheduler(LatencyProfile("episode", tuple(1000 * d for d in ep.d_infer_s)), ep.max_batch_size)


class ReplayScheduler(Scheduler):
    """Dispatches a fixed list of batches (robot indices), one per call: replays a plan.

    An empty batch ``()`` is the idle action (a plan of :func:`solve` with ``idle=True``): the
    device waits until the next observation lands (through the dispatch-timing hook, so
    :func:`play` drives it like any scheduler that waits).

    A plan from :func:`solve` stops at the last decision whose chunks can still arrive before
    the horizon; later decisions cannot change the episode's value, so past the plan's end the
    replay serves the first useful robot (work conservation still asks for a batch).
    """

    def __init__(self, plan: Sequence[Sequence[int]], max_batch_size: int) -> None:
        super().__init__(LatencyProfile("replay", (1.0,)), max_batch_size)
        self.plan = [tuple(b) for b in plan]
        self._next = 0
        self._idle = False
        if any(not b for b in self.plan):
            self.max_wait_s = math.inf  # the plan's own waits end at the next observation

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        if self._next >= len(self.plan):
            return [next(r for r in robots if r.is_useful())]
        batch = self.plan[self._next]
        self._next += 1
        if not batch:
            self._idle = True
            return [next(r for r in robots if r.is_useful())]  # not dispatched: hold() says wait
        return [robots[j] for j in batch]

    def hold(self, robots: Sequence[RobotMirror], batch: Sequence[RobotMirror], now: float) -> float | None:
        if not self._idle:
            return None
        self._idle = False
        return now + _FAR_S  # the driver plans again when the next observation lands


# --------------------------------------------------------------------------------------------
# Search state: one robot relative to its latest observation
#
# A robot's state at a decision is ``(chunks, since)``. ``chunks`` is its queue on its tick grid
# with index 0 = its latest observed index and tick 0 = that observation's tick, reduced to a
# canonical form: what matters for the future is, at every tick, the *union* of indices covered
# by the chunks arrived by then (advance() follows covered stretches, whichever chunk covers
# them), so the queue is stored as the new covered intervals per arrival tick. ``since`` is the
# number of steps executed since the last served observation (``FREE`` once it no longer
# matters for usefulness). Indices below 0 and ticks before 0 are irrelevant and clipped.

RobotState = tuple[tuple[tuple[int, int, int], ...], int]
NO_OBS: RobotState = ((), -2)  # no observation reached the server yet


def canonical(chunks: Sequence[tuple[int, int, int]]) -> tuple[tuple[int, int, int], ...]:
    """Reduce ``(start, end, arrival)`` chunks (relative) to the canonical union-per-arrival form."""
    by_arrival: dict[int, list[tuple[int, int]]] = {}
    for s, e, a in chunks:
        s = max(s, 0)
        if e > s:
            by_arrival.setdefault(max(a, 0), []).append((s, e))
    covered: list[tuple[int, int]] = []  # union so far, sorted disjoint intervals
    out: list[tuple[int, int, int]] = []
    for a in sorted(by_arrival):
        for s, e in _union(by_arrival[a]):
            for ns, ne in _minus(s, e, covered):
                out.append((ns, ne, a))
        covered = _union(covered + by_arrival[a])
    out.sort()
    return tuple(out)


def _union(intervals: list[tuple[int, int]]) -> list[tuple[int, int]]:
    merged: list[tuple[int, int]] = []
    for s, e in sorted(intervals):
        if merged and s <= merged[-1][1]:
            if e > merged[-1][1]:
                merged[-1] = (merged[-1][0], e)
        else:
            merged.append((s, e))
    return merged


def _minus(s: int, e: int, covered: list[tuple[int, int]]) -> list[tuple[int, int]]:
    parts = []
    cur = s
    for cs, ce in covered:
        if ce <= cur or cs >= e:
            continue
        if cs > cur:
            parts.append((cur, cs))
        cur = max(cur, ce)
        if cur >= e:
            break
    if cur < e:
        parts.append((cur, e))
    return parts


@lru_cache(maxsize=1 << 19)
def _run(state: RobotState, ticks: int, hm: int) -> tuple[int, RobotState]:
    """Run ``ticks`` ticks of a robot in ``state`` (via advance()): (executed steps, new state)."""
    chunks, since = state
    if since == NO_OBS[1]:
        return 0, ((), FREE)  # first observation: index 0, never served
    done = advance(0, chunks, ticks)
    moved = canonical([(s - done, e - done, a - ticks) for s, e, a in chunks]) if ticks or done else chunks
    if since != FREE:
        since = FREE if since + done >= hm else since + done
    return done, (moved, since)


@lru_cache(maxsize=1 << 19)
def _executed(chunks: tuple[tuple[int, int, int], ...], ticks: int) -> int:
    return advance(0, chunks, ticks) if ticks > 0 else 0


@lru_cache(maxsize=1 << 19)
def _served(moved: RobotState, done: int, h: int, arrival: int, hm: int) -> RobotState:
    """State after a move of ``done`` steps for a robot that was served at the move's start.

    The chunk starts at the index held before the move (relative: ``-done``) and arrives at
    ``arrival`` (relative to the tick after the move); it cannot arrive during the move (the
    move ends at the latest observation, before any chunk of this batch lands), so serving then
    moving equals moving then adding the chunk.
    """
    chunks, _ = moved
    return canonical([*chunks, (-done, h - done, arrival)]), (FREE if done >= hm else done)


@lru_cache(maxsize=4096)
def _count_vectors(sizes: tuple[int, ...], cap: int) -> tuple[tuple[int, ...], ...]:
    """How many robots to take from each group: every vector with 1 <= sum <= cap."""
    out: list[tuple[int, ...]] = [()]
    for size in sizes:
        out = [(*v, c) for v in out for c in range(min(size, cap - sum(v)) + 1)]
    return tuple(v for v in out if sum(v) > 0)


# --------------------------------------------------------------------------------------------
# The branch-and-bound


@dataclass
class OptimumResult:
    """Outcome of :func:`solve` (values are weighted executed seconds of the scored window).

    Attributes:
        value: the optimum if ``exact``; otherwise the best value found (a lower bound).
        upper_bound: a proven upper bound on the optimum (== ``value`` when exact).
        exact: True when the search finished (the value is the work-conserving optimum).
        plan: robot indices of every batch after the warm-up of a schedule achieving ``value``
            (replayable with :class:`ReplayScheduler`), or None when the best value came from the incumbent and
            no plan was handed in.
        nodes: decision nodes expanded.
        seconds: wall time of the search.
    """

    value: float
    upper_bound: float
    exact: bool
    plan: list[tuple[int, ...]] | None
    nodes: int
    seconds: float

    @property
    def gap(self) -> float:
        """Relative gap between the bound and the best value (0 when exact)."""
        return 0.0 if self.exact else (self.upper_bound - self.value) / self.upper_bound


class _Search:
    """Depth-first branch-and-bound with a memo of exact values and fail-low upper bounds."""

    def __init__(self, ep: Episode, node_limit: int, time_limit_s: float, idle: bool = False) -> None:
        self.ep = ep
        self.idle = idle  # the device may also wait for the next observation (the idle action)
        self.n = len(ep.specs)
        self.hm = [max(1, s.h_min) for s in ep.specs]
        self.h = [s.h_max for s in ep.specs]
        self.wt = [s.weight / s.fps for s in ep.specs]
        self.nt = [ep.n_ticks(j) for j in range(self.n)]
        # Interchangeable robots: same spec apart from the id, same phase.
        keys = [(s.fps, s.chunk_size, s.h_min, s.h_max, s.weight, ep.phases_s[j]) for j, s in enumerate(ep.specs)]
        order = sorted(set(keys), key=keys.index)
        self.cls = [order.index(k) for k in keys]
        self.memo: dict[tuple, tuple[float, bool, tuple | None]] = {}
        self.nodes = 0
        self.node_limit = node_limit
        self.deadline = time.perf_counter() + time_limit_s
        self.cut = False  # the budget ran out: some nodes were bounded, not searched
        self.best_found = -math.inf
        self._timing: dict[int, tuple] = {}

    # ---- per-decision helpers ------------------------------------------------------------------

    def timing(self, t: float) -> tuple[list[int], list[int], bool]:
        """At decision time ``t``: each robot's latest observed tick (capped at the horizon: later
        ticks earn nothing), the first tick a batch of one dispatched at ``t`` could reach, and
        whether ``t`` is terminal (no chunk dispatched from now on can land before the horizon,
        so no choice matters any more)."""
        key = round(t * 1e9)
        hit = self._timing.get(key)
        if hit is None:
            ep = self.ep
            ks = [min(ep.obs_tick(j, t), self.nt[j]) for j in range(self.n)]
            t1 = t + ep.d_infer_s[0]
            first = [min(ep.arrival_tick(j, t1), self.nt[j]) for j in range(self.n)]
            terminal = t >= ep.horizon_s or all(first[j] >= self.nt[j] for j in range(self.n))
            hit = (ks, first, terminal)
            self._timing[key] = hit
        return hit

    def move(self, states: list[RobotState], ks: list[int], ks2: list[int]) -> tuple[list[RobotState], list[int], float]:
        """Advance every robot from ticks ``ks`` to ``ks2``: (states, executed steps, reward)."""
        out, dones, gain = [], [], 0.0
        for j, st in enumerate(states):
            if ks2[j] > ks[j] and ks2[j] >= 0:
                done, st = _run(st, ks2[j] - max(ks[j], 0), self.hm[j])
                gain += self.wt[j] * done
            else:
                done = 0
            out.append(st)
            dones.append(done)
        return out, dones, gain

    def final(self, states: list[RobotState], ks: list[int]) -> float:
        return sum(
            self.wt[j] * _executed(st[0], self.nt[j] - max(ks[j], 0)) for j, st in enumerate(states) if st != NO_OBS
        )

    def robot_bound(self, j: int, st: RobotState, k: int, first: int) -> float:
        """Admissible for one robot: its queue until ``first`` (the earliest tick a new chunk could
        land), then every tick until the horizon."""
        return self.wt[j] * (_executed(st[0], first - max(k, 0)) + self.nt[j] - first)

    def key(self, t: float, states: list[RobotState]) -> tuple:
        return (round(t * 1e9), tuple(sorted(zip(self.cls, states, strict=True))))

    def useful(self, states: list[RobotState]) -> list[int]:
        return [j for j, st in enumerate(states) if st[1] == FREE]

    def batches(self, states: list[RobotState], useful: list[int]) -> list[tuple[int, ...]]:
        """Every batch up to symmetry: counts per class of interchangeable useful robots."""
        groups: dict[tuple, list[int]] = {}
        for j in useful:
            groups.setdefault((self.cls[j], states[j]), []).append(j)
        members = list(groups.values())
        out = []
        for counts in _count_vectors(tuple(len(m) for m in members), self.ep.max_batch_size):
            batch: list[int] = []
            for m, c in zip(members, counts, strict=True):
                batch += m[:c]
            out.append(tuple(sorted(batch)))
        return out

    def after(self, states: list[RobotState], ks: list[int], t: float, size: int):
        """What every child of batch size ``size`` shares: the next decision time, every robot
        moved there unserved, the reward on the way, the new ticks, and each robot's bound."""
        t2 = t + self.ep.d_infer_s[size - 1]
        ks2, first2, terminal2 = self.timing(t2)
        moved, dones, gain = self.move(states, ks, ks2)
        arrivals = [self.ep.arrival_tick(j, t2) - max(ks2[j], 0) for j in range(self.n)]
        bounds = None
        if not terminal2:
            bounds = [self.robot_bound(j, moved[j], ks2[j], first2[j]) for j in range(self.n)]
            bounds.append(sum(bounds))  # bounds[-1]: the fleet's bound if nobody were served
        return t2, ks2, first2, terminal2, moved, dones, gain, arrivals, bounds

    def served_state(self, j: int, moved: list[RobotState], dones: list[int], arrivals: list[int]) -> RobotState:
        return _served(moved[j], dones[j], self.h[j], arrivals[j], self.hm[j])

    def child(self, states: list[RobotState], ks: list[int], t: float, batch: tuple[int, ...]):
        """(next time, next states, next ticks, reward on the way) after dispatching ``batch``."""
        t2, ks2, _, _, moved, dones, gain, arrivals, _ = self.after(states, ks, t, len(batch))
        nxt = list(moved)
        for j in batch:
            nxt[j] = self.served_state(j, moved, dones, arrivals)
        return t2, nxt, ks2, gain

    # ---- the recursion ---------------------------------------------------------------------

    def value(self, t: float, states: list[RobotState], ks: list[int], alpha: float, acc: float) -> tuple[float, bool]:
        """Best future reward from this decision: (value, exact). Not exact means "at most value".

        ``alpha`` is the future reward this node must beat to matter; ``acc`` the reward
        already collected on the path (only to track the best complete schedule found).
        """
        ep = self.ep
        gained = 0.0
        while True:  # idle jumps: nobody useful, wait for the next observation
            _, first, terminal = self.timing(t)
            if terminal:
                v = self.final(states, ks)
                self.best_found = max(self.best_found, acc + gained + v)
                return gained + v, True
            useful = self.useful(states)
            if useful:
                break
            t2 = ep.next_observation(t)
            ks2 = self.timing(t2)[0]
            states, _, g = self.move(states, ks, ks2)
            ks = ks2
            t = t2
            gained += g
        alpha -= gained
        acc += gained
        v, exact = self.decide(t, states, ks, alpha, acc, first)
        return gained + v, exact

    def decide(
        self, t: float, states: list[RobotState], ks: list[int], alpha: float, acc: float, first: list[int]
    ) -> tuple[float, bool]:
        key = self.key(t, states)
        hit = self.memo.get(key)
        if hit is not None and (hit[1] or hit[0] <= alpha):
            if hit[1]:
                self.best_found = max(self.best_found, acc + hit[0])
            return hit[0], hit[1]
        if self.cut or self.nodes >= self.node_limit or (self.nodes & 255 == 0 and time.perf_counter() > self.deadline):
            self.cut = True
            return sum(self.robot_bound(j, st, ks[j], first[j]) for j, st in enumerate(states)), False
        self.nodes += 1
        useful = self.useful(states)
        shared = {}
        delta: dict[tuple[int, int], float] = {}  # (size, robot): bound change when served
        kids = []
        for batch in self.batches(states, useful):
            size = len(batch)
            if size not in shared:
                shared[size] = self.after(states, ks, t, size)
            t2, ks2, first2, terminal2, moved, dones, gain, arrivals, bounds = shared[size]
            if terminal2:
                nxt = list(moved)
                for j in batch:
                    nxt[j] = self.served_state(j, moved, dones, arrivals)
                ub = gain + self.final(nxt, ks2)
            else:
                ub = gain + bounds[-1]
                for j in batch:
                    d = delta.get((size, j))
                    if d is None:
                        served = self.served_state(j, moved, dones, arrivals)
                        d = delta[(size, j)] = self.robot_bound(j, served, ks2[j], first2[j]) - bounds[j]
                    ub += d
            kids.append((ub, size, batch))
        if self.idle:
            # The idle action: dispatch nothing, wait for the next observation arrival.
            idle = self.wait(states, ks, t)
            t2, ks2, moved, g, first2, terminal2 = idle
            ub = g + (self.final(moved, ks2) if terminal2 else sum(self.robot_bound(j, st, ks2[j], first2[j]) for j, st in enumerate(moved)))
            kids.append((ub, 0, ()))
        kids.sort(key=lambda c: -c[0])
        best_exact, best_batch, top = -math.inf, None, -math.inf
        for ub, size, batch in kids:
            floor = max(alpha, best_exact)
            if ub <= floor:
                top = max(top, ub)  # cannot matter: its bound is all we claim about it
                continue
            if size == 0:
                t2, ks2, st2, g, _, _ = idle
            else:
                t2, ks2, _, _, moved, dones, g, arrivals, _ = shared[size]
                st2 = list(moved)
                for j in batch:
                    st2[j] = self.served_state(j, moved, dones, arrivals)
            v, exact = self.value(t2, st2, ks2, floor - g, acc + g)
            total = g + v
            top = max(top, total)
            if exact and total > best_exact:
                best_exact, best_batch = total, batch
        exact = best_exact >= top - 1e-9  # totals are (floor - g) + g: allow float rounding
        value = best_exact if exact else top
        action = tuple(sorted((self.cls[j], states[j]) for j in best_batch)) if exact and best_batch is not None else None
        self.memo[key] = (value, exact, action)
        return value, exact

    def wait(self, states: list[RobotState], ks: list[int], t: float):
        """The idle action at ``t``: (next observation time, its ticks, every robot moved there,
        the reward on the way, the first ticks reachable from there, whether it is terminal)."""
        t2 = self.ep.next_observation(t)
        ks2, first2, terminal2 = self.timing(t2)
        moved, _, g = self.move(states, ks, ks2)
        return t2, ks2, moved, g, first2, terminal2

    def start(self, warmup: Sequence[tuple[int, ...]]) -> tuple[float, list[RobotState], list[int], float]:
        """Replay the warm-up's batches from the cold start (t = 0, no observation yet): the time,
        states and ticks of the first decision that is the schedule's own, and the reward so far."""
        n = self.n
        t = 0.0
        ks = self.timing(t)[0]
        states, _, acc = self.move([NO_OBS] * n, [-1] * n, ks)
        for batch in warmup:
            while not self.useful(states):  # the device idles until an observation lands
                t2 = self.ep.next_observation(t)
                ks2 = self.timing(t2)[0]
                states, _, g = self.move(states, ks, ks2)
                t, ks, acc = t2, ks2, acc + g
            t, states, ks, g = self.child(states, ks, t, batch)
            acc += g
        return t, states, ks, acc

    def plan(self, warmup: Sequence[tuple[int, ...]]) -> list[tuple[int, ...]]:
        """Follow the memo's best batches from the end of the warm-up (only after an exact solve)."""
        ep = self.ep
        t, states, ks, _ = self.start(warmup)
        out: list[tuple[int, ...]] = []
        while not self.timing(t)[2]:
            useful = self.useful(states)
            if not useful:
                t2 = ep.next_observation(t)
                ks2 = self.timing(t2)[0]
                states, _, _ = self.move(states, ks, ks2)
                t, ks = t2, ks2
                continue
            entry = self.memo.get(self.key(t, states))
            if entry is None or entry[2] is None:
                raise RuntimeError("the optimal path left the memo (plan requested from an inexact search)")
            if entry[2] == ():  # the idle action
                out.append(())
                t, ks, states, _, _, _ = self.wait(states, ks, t)
                continue
            wanted = list(entry[2])
            batch = []
            for j in useful:
                if (self.cls[j], states[j]) in wanted:
                    wanted.remove((self.cls[j], states[j]))
                    batch.append(j)
            out.append(tuple(batch))
            t, states, ks, _ = self.child(states, ks, t, tuple(batch))
        return out


def solve(
    episode: Episode,
    incumbent: float = -math.inf,
    incumbent_plan: Sequence[Sequence[int]] | None = None,
    node_limit: int = 2_000_000,
    time_limit_s: float = 120.0,
    idle: bool = False,
) -> OptimumResult:
    """Best schedule of ``episode`` (see the module docstring): the best work-conserving one, or
    with ``idle=True`` the best of all, the device may also wait for the next observation at
    any decision (the *true* optimum; its plan holds ``()`` for each wait).

    Args:
        incumbent: a value some schedule is known to reach on this episode (e.g. the best online
            scheduler's); it prunes the search and is the lower bound if the budget runs out.
        incumbent_plan: that schedule's batches after the warm-up, returned as the plan when
            nothing beats it.
        node_limit / time_limit_s: search budget; when it runs out the result carries a proven
            upper bound instead of the exact optimum.
    """
    start = time.perf_counter()
    search = _Search(episode, node_limit, time_limit_s, idle)
    # The warm-up is EDF's and the same for every schedule: replay it, then search. The search
    # counts reward from t = 0; ``before`` (the reward of the ticks before the scored window)
    # converts between the two.
    warm = play(episode, _ColdEdf(episode))
    warmup = warm.batches[: warm.warmup_decisions]
    before = warm.warmup_weighted_s
    t, states, ks, acc = search.start(warmup)
    value, exact = search.value(t, states, ks, incumbent + before - acc - 1e-9, acc)
    value += acc - before
    found = max(search.best_found - before, incumbent)
    if exact:
        best, upper, plan = value, value, search.plan(warmup)
    elif value <= incumbent + 1e-9:
        # Every schedule is bounded by the incumbent's value: the incumbent is optimal.
        best, upper, exact = incumbent, incumbent, True
        plan = [tuple(b) for b in incumbent_plan] if incumbent_plan is not None else None
    else:
        best, upper = found, value
        plan = [tuple(b) for b in incumbent_plan] if incumbent_plan is not None and found == incumbent else None
    return OptimumResult(best, upper, exact, plan, search.nodes, time.perf_counter() - start)

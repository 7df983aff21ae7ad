"""Offline optimum for small fleets: the best work-conserving schedule of a deterministic episode.

What is optimised. A deterministic :class:`Episode` fixes everything a schedule cannot change:
the robots (SPEC §1 specs, weights included), the latency profile ``d_infer(b)``, a jitter-free
network (every one-way delay is exactly ``net_s``, so the mirror is exact), each robot's tick
phase (all 0 by default: a synchronous cold start with empty queues) and a horizon ``T``. A
*schedule* is the sequence of batches dispatched at the instants the device becomes free, under
the same rules every online scheduler obeys (SPEC §3): a batch is a non-empty set of at most
``b`` distinct *useful* robots, and the device is **work-conserving**, i.e. it dispatches
whenever some robot is useful and otherwise waits for the next observation. The optimum is the
schedule that maximises the SPEC §2 reward summed over the episode, i.e. the weighted executed
robot time ``Σ_j w_j · (steps executed before T) / fps_j``. Schedules that idle on purpose while
a robot is useful are *not* in the search space (no online scheduler may do that either), so
"optimal" here means optimal among work-conserving schedules.

How. Depth-first branch-and-bound over batch choices (every subset of the useful robots of size
``1..b``, so the batch size is chosen too), with

- the transition of :func:`lerobot_armory.mirror.advance` (never re-implemented): each robot's
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

Every value the search reports can be checked: :func:`play` drives the real
:class:`~lerobot_armory.mirror.RobotMirror` / :class:`~lerobot_armory.mirror.RobotTimeline`
objects with any scheduler on the same episode, and :class:`ReplayScheduler` replays the
optimal plan through it (the test suite checks the two agree to the last step).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

from lerobot_armory.errors import ConfigError
from lerobot_armory.latency import LatencyProfile, load_profile
from lerobot_armory.mirror import Chunk, DelayEstimator, RobotMirror, RobotSpec, RobotTimeline, advance, tick_of
from lerobot_armory.schedulers.base import Scheduler, check_batch
from lerobot_armory.sim.presets import fleet_specs, get_preset

# Same tolerance as the mirror's tick mapping: an observation captured exactly ``net_s`` before
# a decision has reached the server.
_EPS = 1e-9

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
    """

    specs: tuple[RobotSpec, ...]
    d_infer_s: tuple[float, ...]
    horizon_s: float
    net_s: float
    phases_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not self.specs:
            raise ConfigError("robots", "the fleet is empty")
        if len({s.robot_id for s in self.specs}) != len(self.specs):
            raise ConfigError("robots", "robot ids must be unique")
        if not self.d_infer_s or any(not d > 0 for d in self.d_infer_s):
            raise ConfigError("latency_profile", "d_infer must be positive for every batch size")
        if not (math.isfinite(self.horizon_s) and self.horizon_s > 0):
            raise ConfigError("horizon_s", f"must be > 0, got {self.horizon_s}")
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
        """Weighted executed time if no robot ever starved (the trivial ceiling)."""
        return sum(s.weight * self.n_ticks(j) / s.fps for j, s in enumerate(self.specs))


def episode_for(
    preset: str,
    mix: str,
    robots: int,
    horizon_s: float,
    fast_weight: float = 1.0,
    latency_profile: str | LatencyProfile | None = None,
    max_batch_size: int | None = None,
    net_median_ms: float | None = None,
) -> Episode:
    """The deterministic episode of a preset fleet (SPEC §5 timing, σ = 0, synchronous start).

    The network delay is the preset's median without jitter; the batch cap and latency profile
    default to the preset's.
    """
    p = get_preset(preset)
    profile = latency_profile if isinstance(latency_profile, LatencyProfile) else load_profile(latency_profile or p.latency_profile)
    cap = p.default_batch_cap(mix) if max_batch_size is None else max_batch_size
    if cap < 1:
        raise ConfigError("max_batch_size", f"must be >= 1, got {cap}")
    median = p.net_median_ms if net_median_ms is None else net_median_ms
    return Episode(
        tuple(fleet_specs(p, mix, robots, fast_weight)), tuple(profile.table_s(cap)), horizon_s, median / 1000.0
    )


# --------------------------------------------------------------------------------------------
# Playing a scheduler on an episode (the real mirror objects)


@dataclass
class EpisodeResult:
    """What one schedule achieved on an episode.

    Attributes:
        executed_steps / ticks: per robot, steps executed and ticks before the horizon.
        weighted_executed_s: SPEC §2 reward summed over the episode.
        batches: robot indices of every dispatched batch, in order.
    """

    episode: Episode
    executed_steps: list[int]
    ticks: list[int]
    weighted_executed_s: float
    batches: list[tuple[int, ...]] = field(default_factory=list)

    def starvation_pct(self, j: int) -> float:
        """Starved ticks of robot ``j`` in % of its ticks."""
        return 100.0 * (self.ticks[j] - self.executed_steps[j]) / self.ticks[j] if self.ticks[j] else 0.0

    def tier_starvation_pct(self, tier: str) -> float:
        """Mean starvation of the robots of ``tier`` (NaN if none)."""
        rows = [self.starvation_pct(j) for j, s in enumerate(self.episode.specs) if s.tier == tier]
        return sum(rows) / len(rows) if rows else float("nan")


def play(episode: Episode, scheduler: Scheduler) -> EpisodeResult:
    """Run ``scheduler`` on ``episode`` with the real mirror and ground-truth timeline classes.

    This is the simulator's event loop (SPEC §3 work conservation, latest observation per robot,
    chunk ``(î_j, h_max, t_done + d_action)``) without randomness: delays are exact, so the
    mirror's delay estimate is exact from the start (one registration exchange) and needs no
    execution reports. ``FleetSimulator`` with ``net_sigma = 0`` and the same phases gives the
    same executed steps (checked in the tests).
    """
    ep = episode
    n = len(ep.specs)
    m = ep.net_s
    if scheduler.max_batch_size != ep.max_batch_size:
        raise ConfigError("max_batch_size", f"scheduler cap {scheduler.max_batch_size} != episode cap {ep.max_batch_size}")
    truth = [RobotTimeline(s.fps, ep.phases_s[j]) for j, s in enumerate(ep.specs)]
    mirrors = []
    for s in ep.specs:
        est = DelayEstimator()
        est.add_exchange(-1.0, -1.0 + m, -1.0 + m, -1.0 + 2 * m)  # offset 0, one-way exactly m
        mirrors.append(RobotMirror(s, est))
    position = {id(r): j for j, r in enumerate(mirrors)}
    fed = [-1] * n
    batches: list[tuple[int, ...]] = []
    name = type(scheduler).__name__
    t = 0.0
    while t < ep.horizon_s:
        for j, s in enumerate(ep.specs):
            k = ep.obs_tick(j, t)
            if k > fed[j]:
                truth[j].run_to(k)
                fed[j] = k
                capture = ep.phases_s[j] + k / s.fps
                mirrors[j].on_observation(truth[j].index, capture, ep.obs_arrival(j, k))
        if any(r.is_useful() for r in mirrors):
            batch = scheduler.select(mirrors, t)
            check_batch(batch, scheduler.max_batch_size, name)
            t_done = t + ep.d_infer_s[len(batch) - 1]
            chosen = []
            for r in batch:
                j = position[id(r)]
                chunk = r.on_dispatch(t_done)
                truth[j].add_chunk(Chunk(chunk.chunk_id, chunk.i_start, chunk.h, t_done + m))
                chosen.append(j)
            batches.append(tuple(chosen))
            t = t_done
        else:
            t = ep.next_observation(t)
    ticks = [ep.n_ticks(j) for j in range(n)]
    for j in range(n):
        truth[j].run_to(ticks[j])
    executed = [tl.index for tl in truth]
    value = sum(s.weight * executed[j] / s.fps for j, s in enumerate(ep.specs))
    return EpisodeResult(ep, executed, ticks, value, batches)


class ReplayScheduler(Scheduler):
    """Dispatches a fixed list of batches (robot indices), one per call: replays a plan.

    A plan from :func:`solve` stops at the last decision whose chunks can still arrive before
    the horizon; later decisions cannot change the episode's value, so past the plan's end the
    replay serves the first useful robot (work conservation still asks for a batch).
    """

    def __init__(self, plan: Sequence[Sequence[int]], max_batch_size: int) -> None:
        super().__init__(LatencyProfile("replay", (1.0,)), max_batch_size)
        self.plan = [tuple(b) for b in plan]
        self._next = 0

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        if self._next >= len(self.plan):
            return [next(r for r in robots if r.is_useful())]
        batch = self.plan[self._next]
        self._next += 1
        return [robots[j] for j in batch]


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


@lru_cache(maxsize=1 << 20)
def _run(state: RobotState, ticks: int, hm: int) -> tuple[int, RobotState]:
    """Run ``ticks`` ticks of a robot in ``state`` (via advance()): (executed steps, new state)."""
    chunks, since = state
    if since == NO_OBS[1]:
        return 0, ((), FREE)  # first observation: index 0, never served
    done = advance(0, chunks, ticks)
    moved = canonical([(s - done, e - done, a - ticks) for s, e, a in chunks])
    if since != FREE:
        since = FREE if since + done >= hm else since + done
    return done, (moved, since)


@lru_cache(maxsize=1 << 20)
def _executed(chunks: tuple[tuple[int, int, int], ...], ticks: int) -> int:
    return advance(0, chunks, ticks) if ticks > 0 else 0


@lru_cache(maxsize=1 << 20)
def _serve(state: RobotState, h: int, arrival: int) -> RobotState:
    chunks, _ = state
    return canonical([*chunks, (0, h, arrival)]), 0


# --------------------------------------------------------------------------------------------
# The branch-and-bound


@dataclass
class OptimumResult:
    """Outcome of :func:`solve`.

    Attributes:
        value: the optimum if ``exact``; otherwise the best value found (a lower bound).
        upper_bound: a proven upper bound on the optimum (== ``value`` when exact).
        exact: True when the search finished (the value is the work-conserving optimum).
        plan: robot indices of every batch of a schedule achieving ``value`` (replayable with
            :class:`ReplayScheduler`), or None when the best value came from the incumbent and
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

    def __init__(self, ep: Episode, node_limit: int, time_limit_s: float) -> None:
        self.ep = ep
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

    # ---- per-decision helpers ------------------------------------------------------------------

    def ticks(self, t: float) -> list[int]:
        return [self.ep.obs_tick(j, t) for j in range(self.n)]

    def move(self, states: list[RobotState], ks: list[int], t2: float) -> tuple[list[RobotState], list[int], float]:
        """Advance every robot to its latest observation at ``t2``: (states, ticks, reward gained)."""
        out, ks2, gain = [], [], 0.0
        for j, st in enumerate(states):
            # Ticks at or after the horizon earn nothing (t2 may lie past it).
            k2 = min(self.ep.obs_tick(j, t2), self.nt[j])
            if k2 > ks[j] and k2 >= 0:
                # A robot's first observation finds it at index 0 (no chunk yet): nothing ran.
                done, st = _run(st, k2 - max(ks[j], 0), self.hm[j])
                gain += self.wt[j] * done
                ks2.append(k2)
            else:
                ks2.append(ks[j])
            out.append(st)
        return out, ks2, gain

    def terminal(self, t: float) -> bool:
        """No chunk dispatched at ``t`` or later can arrive before the horizon: choices are moot."""
        if t >= self.ep.horizon_s:
            return True
        t_done = t + self.ep.d_infer_s[0]
        return all(self.ep.arrival_tick(j, t_done) >= self.nt[j] for j in range(self.n))

    def final(self, states: list[RobotState], ks: list[int]) -> float:
        return sum(
            self.wt[j] * _executed(st[0], self.nt[j] - max(ks[j], 0)) for j, st in enumerate(states) if st != NO_OBS
        )

    def bound(self, states: list[RobotState], ks: list[int], t: float) -> float:
        """Admissible: current queue until the first possible new arrival, every tick after it."""
        t_done = t + self.ep.d_infer_s[0]
        total = 0.0
        for j, st in enumerate(states):
            k = max(ks[j], 0)
            first = min(self.ep.arrival_tick(j, t_done), self.nt[j])
            total += self.wt[j] * (_executed(st[0], first - k) + self.nt[j] - first)
        return total

    def key(self, t: float, states: list[RobotState]) -> tuple:
        return (round(t * 1e9), tuple(sorted(zip(self.cls, states, strict=True))))

    def useful(self, states: list[RobotState]) -> list[int]:
        return [j for j, st in enumerate(states) if st[1] == FREE]

    def batches(self, states: list[RobotState], useful: list[int]) -> Iterator[tuple[int, ...]]:
        """Every batch up to symmetry: counts per class of interchangeable useful robots."""
        groups: dict[tuple, list[int]] = {}
        for j in useful:
            groups.setdefault((self.cls[j], states[j]), []).append(j)
        members = list(groups.values())
        cap = self.ep.max_batch_size

        def rec(g: int, left: int, chosen: list[int]) -> Iterator[tuple[int, ...]]:
            if g == len(members):
                if chosen:
                    yield tuple(sorted(chosen))
                return
            for c in range(min(left, len(members[g])) + 1):
                yield from rec(g + 1, left - c, chosen + members[g][:c])

        yield from rec(0, cap, [])

    def child(self, states: list[RobotState], ks: list[int], t: float, batch: tuple[int, ...]):
        t_done = t + self.ep.d_infer_s[len(batch) - 1]
        served = list(states)
        for j in batch:
            served[j] = _serve(states[j], self.h[j], self.ep.arrival_tick(j, t_done) - max(ks[j], 0))
        return (t_done, *self.move(served, ks, t_done))

    # ---- the recursion ---------------------------------------------------------------------

    def value(self, t: float, states: list[RobotState], ks: list[int], alpha: float, acc: float) -> tuple[float, bool]:
        """Best future reward from this decision: (value, exact). Not exact means "at most value".

        ``alpha`` is the future reward this node must beat to matter; ``acc`` the reward
        already collected on the path (only to track the best complete schedule found).
        """
        ep = self.ep
        while True:  # idle jumps: nobody useful, wait for the next observation
            if self.terminal(t):
                v = self.final(states, ks)
                self.best_found = max(self.best_found, acc + v)
                return v, True
            useful = self.useful(states)
            if useful:
                break
            t2 = ep.next_observation(t)
            states, ks, g = self.move(states, ks, t2)
            acc += g
            alpha -= g
            v, exact = self.value(t2, states, ks, alpha, acc)
            return g + v, exact
        key = self.key(t, states)
        hit = self.memo.get(key)
        if hit is not None and (hit[1] or hit[0] <= alpha):
            if hit[1]:
                self.best_found = max(self.best_found, acc + hit[0])
            return hit[0], hit[1]
        if self.cut or self.nodes >= self.node_limit or (self.nodes & 1023 == 0 and time.perf_counter() > self.deadline):
            self.cut = True
            return self.bound(states, ks, t), False
        self.nodes += 1
        kids = []
        for batch in self.batches(states, useful):
            t2, st2, ks2, g = self.child(states, ks, t, batch)
            kids.append((g + self.bound(st2, ks2, t2) if not self.terminal(t2) else g + self.final(st2, ks2), g, batch, t2, st2, ks2))
        kids.sort(key=lambda c: -c[0])
        best_exact, best_batch, top = -math.inf, None, -math.inf
        for ub, g, batch, t2, st2, ks2 in kids:
            floor = max(alpha, best_exact)
            if ub <= floor:
                top = max(top, ub)  # cannot matter: its bound is all we claim about it
                continue
            v, exact = self.value(t2, st2, ks2, floor - g, acc + g)
            total = g + v
            top = max(top, total)
            if exact and total > best_exact:
                best_exact, best_batch = total, batch
        exact = best_exact >= top - 1e-9  # totals are (floor - g) + g: allow float rounding
        value = best_exact if exact else top
        action = tuple(sorted((self.cls[j], states[j]) for j in best_batch)) if exact and best_batch else None
        self.memo[key] = (value, exact, action)
        return value, exact

    def plan(self) -> list[tuple[int, ...]]:
        """Follow the memo's best batches from the start (only valid after an exact solve)."""
        ep = self.ep
        t = 0.0
        states = [NO_OBS] * self.n
        ks = [-1] * self.n
        states, ks, _ = self.move(states, ks, t)
        out: list[tuple[int, ...]] = []
        while not self.terminal(t):
            useful = self.useful(states)
            if not useful:
                t2 = ep.next_observation(t)
                states, ks, _ = self.move(states, ks, t2)
                t = t2
                continue
            entry = self.memo.get(self.key(t, states))
            if entry is None or entry[2] is None:
                raise RuntimeError("the optimal path left the memo (plan requested from an inexact search)")
            wanted = list(entry[2])
            batch = []
            for j in useful:
                if (self.cls[j], states[j]) in wanted:
                    wanted.remove((self.cls[j], states[j]))
                    batch.append(j)
            batch_t = tuple(batch)
            out.append(batch_t)
            t, states, ks, _ = self.child(states, ks, t, batch_t)
        # Decisions after the last one that matters still happen in a real run; any batch does.
        return out


def solve(
    episode: Episode,
    incumbent: float = -math.inf,
    incumbent_plan: Sequence[Sequence[int]] | None = None,
    node_limit: int = 2_000_000,
    time_limit_s: float = 120.0,
) -> OptimumResult:
    """Best work-conserving schedule of ``episode`` (see the module docstring).

    Args:
        incumbent: a value some schedule is known to reach on this episode (e.g. the best online
            scheduler's); it prunes the search and is the lower bound if the budget runs out.
        incumbent_plan: that schedule's batches, returned as the plan when nothing beats it.
        node_limit / time_limit_s: search budget; when it runs out the result carries a proven
            upper bound instead of the exact optimum.
    """
    start = time.perf_counter()
    search = _Search(episode, node_limit, time_limit_s)
    states, ks, _ = search.move([NO_OBS] * search.n, [-1] * search.n, 0.0)
    # Work conservation from t = 0: nobody holds an observation before the first one arrives.
    value, exact = search.value(0.0, states, ks, incumbent - 1e-9, 0.0)
    found = max(search.best_found, incumbent)
    if exact:
        best, upper, plan = value, value, search.plan()
    elif value <= incumbent + 1e-9:
        # Every schedule is bounded by the incumbent's value: the incumbent is optimal.
        best, upper, exact = incumbent, incumbent, True
        plan = [tuple(b) for b in incumbent_plan] if incumbent_plan is not None else None
    else:
        best, upper = found, value
        plan = [tuple(b) for b in incumbent_plan] if incumbent_plan is not None and found == incumbent else None
    return OptimumResult(best, upper, exact, plan, search.nodes, time.perf_counter() - start)

"""Rollout: score each candidate first batch by playing the mirror forward under a base policy.

Lookahead (SPEC §3) scores a batch by what it adds inside a 1 s window, per GPU-second, one
epoch deep. That misses what the offline optimum (:mod:`lerobot_armory.sim.optimal`) exploits:
a batch decides *when the device is next free* and so shapes every later batch (small staggered
batches keep latency low while the fleet can be kept fed; full batches keep the throughput up
once it cannot), and it decides which robots are useful later. Rollout measures that directly:

1. **Candidates.** Lookahead's best batch of every size ``s`` (the ``s`` largest weighted
   marginal gains, so weights and the freshness of each robot's observation count), EDF's full
   batch, and the *due* batch (the robots that starve unless served now, :meth:`~RolloutScheduler._due`).
   They are ordered by Lookahead's score and at most ``candidates`` are rolled out.
2. **Rollout.** Each candidate is dispatched on a copy of the fleet's mirror state, then a base
   policy (EDF ordering) plays on until ``window_s`` after the decision, predicting every later
   observation the way Lookahead does (the index the mirror says the robot holds ``d_obs``
   earlier). Two base policies, picked once per decision from the load (``tail=auto``):

   - *due*: each later batch holds only the robots that would starve if left to the batch
     after it (at least one). It keeps batches as small as the fleet allows, which is what the
     optimum does while the fleet can be kept fed.
   - *same*: each later batch is the candidate's size, earliest deadlines first. Used when more
     robots are due than one batch holds (overload): the rollout then asks "what if I keep
     dispatching batches of this size", so a small first batch is charged for the throughput it
     would cost if repeated. (Scoring a small first batch followed by full batches is what made
     an early version pick small batches at every decision and lose throughput under overload.)

   ``tail=same`` always (``--scheduler.tail=same``) is the setting that meets both targets of
   the frontier study (``docs/results/frontier/README.md``): ≥ 95 % of the exact optimum on all
   30 small fleets when told the episode's end as the optimum is (``Scheduler.episode_end_s``:
   the window is clipped there; live it is inf), and better than EDF on both tiers at some
   weight in the four N = 10 one-fast / half-fast fleets. ``auto`` stays the default because
   the *due* tail is better where the device can nearly keep the fleet fed (piper half-fast
   N = 4..5: 100 / 99.7 % of the optimum against 96.4 / 96.5 %).

   Who is first in a later batch (``order``): earliest deadline (``deadline``, EDF, the
   default), or the largest weighted *coverage gain* (``gain``): how much longer the robot's
   queue would last if a full batch dispatched now served it, times its weight. ``gain`` is
   what Lookahead maximises, in closed form; it skips a robot whose queue already reaches past
   what a new chunk would cover, and it makes the rollout's later batches honour the weights,
   where EDF's ignore them. Measured at N = 10 on 48 paired seeds
   (``docs/results/frontier/README.md``): with ``tail=same`` it beats EDF on both tiers, at
   some weight, in all four one-fast / half-fast fleets of both presets, where the default
   wins only the half-fast ones. It is an option, not the default, because it is worse on the
   small fleets against the offline optimum (6 of 30 rows under 95 %, the default 4).
3. **Score.** The fleet's weighted executed robot time in the window (SPEC §2 reward, each
   robot's own weight). The best candidate is dispatched; ties go to the smaller batch.
4. **Kept plan** (``keep_plan``, off by default). The winning rollout's later batches are kept,
   by robot id, and the next decision rolls them out once more as one extra candidate (robots
   gone or not useful by then are left out); the kept plan wins ties. Without it, re-deciding
   at every batch can leave a good plan halfway for one that only looks as good. Measured at
   N = 10 (``docs/results/frontier/README.md``): it moves piper one-fast's fast/slow trade-off
   by about 0.2–0.4 pp past the default's, does nothing measurable for libero one-fast, and
   costs one more rollout per decision, so it is an option.

Decisions depend on nothing but the mirror state, so they are deterministic and the same on
every machine; the cost is bounded by ``candidates`` × the window's epochs (SPEC budget:
≤ 1 ms p99 at N = 10, b = 5; ≤ 10 ms at N = 100, b = 8; see ``benchmarks/decision_time.py``
and ``benchmarks/frontier.py``).

Why it is fast enough. A rollout asks three things about a robot many times: its index at a
tick, when it runs dry, and when it becomes useful again. A chunk made from an observation
starts at or before the index the robot holds when the chunk arrives, so what a robot can
execute is always one stretch ``[index, coverage end)`` that each arrival extends.
:class:`_Robot` therefore keeps a robot as ``(index at tick 0, coverage end, pending arrivals)``
and answers those questions in a loop over its few pending arrivals. That is
:func:`~lerobot_armory.mirror.advance` specialised to such chunk sets (the state is built from
the mirror's window view with ``reach``), and the tests check the two agree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.errors import ConfigError
from lerobot_armory.latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror, TickChunk, reach
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig

TAILS = ("auto", "due", "same")
ORDERS = ("deadline", "gain")

# A robot's queue inside a rollout: (coverage end at tick 0, pending (arrival tick, end) sorted).
Queue = tuple[int, tuple[tuple[int, int], ...]]


def queue_of(index: int, chunks: Sequence[TickChunk]) -> Queue:
    """The rollout form of a robot's chunks on a grid where ``index`` is held before tick 0.

    Valid for chunks that start at or before the index the robot holds when they arrive (every
    chunk made from one of the robot's observations does). Chunks that arrived by tick 0 give
    the coverage end; the others are kept as ``(arrival tick, end)``.
    """
    end0 = reach(index, chunks, 0)
    pending = sorted((a, e) for _, e, a in chunks if a > 0 and e > index)
    return end0, tuple(pending)


def index_at(index: int, queue: Queue, tick: int) -> int:
    """Index held before ``tick`` (ticks ``0 .. tick-1`` run): the robot executes one step per
    tick while its coverage lasts; an arrival extends the coverage (equals ``advance``)."""
    end, pending = queue
    x, at = index, 0
    # min() spelled as conditionals: these loops are the rollout's hot path.
    for a, e in pending:
        if a > tick:
            break
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    x += tick - at
    return x if x < end else end


def dry_tick(index: int, queue: Queue) -> int:
    """Tick at which the robot starves once every pending chunk has arrived: EDF's deadline
    (``ticks_until_dry`` also waits for chunks that land after the robot passed their end)."""
    end, pending = queue
    x, at = index, 0
    for a, e in pending:
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    return at + end - x


def tick_reaching(index: int, queue: Queue, target: int) -> int:
    """First tick before which the robot holds an index >= ``target`` (-1 if it never does)."""
    end, pending = queue
    x, at = index, 0
    if x >= target:
        return 0
    for a, e in pending:
        if end >= target and x + a - at >= target:
            return at + target - x
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    return at + target - x if end >= target else -1


class _Robot:
    """One robot frozen at the decision: its window view in rollout form plus fixed facts."""

    __slots__ = (
        "k", "mirror", "index", "queue", "origin", "fps", "one_way", "h", "hm", "wpt", "last", "obs",
        "ticks", "useful", "deadline", "base", "ready", "gains", "i", "span", "weight",
    )  # fmt: skip

    def __init__(self, k: int, mirror: RobotMirror, now: float, horizon_s: float) -> None:
        view = mirror.window_view(now, horizon_s)
        spec = mirror.spec
        self.k = k
        self.mirror = mirror
        self.index = view.index
        self.queue = queue_of(view.index, view.chunks)
        self.origin = view.origin_time
        self.fps = spec.fps
        self.one_way = mirror.estimator.one_way_s
        self.h = spec.h_max
        self.hm = max(1, spec.h_min)
        self.wpt = spec.weight / spec.fps
        self.last = mirror.last_served_index
        self.obs = mirror.obs_index
        self.ticks = view.window_ticks
        self.useful = mirror.is_useful()
        # EDF's deadline (when the queue runs dry). A robot already dry keeps its true past
        # deadline, so the one starving longest comes first, as in EDF.
        dry = dry_tick(self.index, self.queue)
        self.deadline = self.origin + dry / self.fps if dry > 0 else mirror.deadline()
        self.base = index_at(self.index, self.queue, self.ticks) - self.index
        # A robot that is not useful now becomes useful once it holds last + h_min and the
        # observation of that tick has reached the server.
        self.ready = -math.inf
        if not self.useful:
            target = (self.last if self.last is not None else self.index) + self.hm
            self.ready = self.useful_from(tick_reaching(self.index, self.queue, target))
        self.gains: list[float] = []
        self.i = -1  # position in the decision's pool: the rollout's per-robot lists use it
        # For the gain order: a chunk from an observation captured one-way before t covers
        # until t + span.
        self.span = self.h / self.fps - self.one_way
        self.weight = spec.weight

    def useful_from(self, tick: int) -> float:
        """Server time from which the observation of ``tick`` is held (inf for tick -1: never)."""
        return math.inf if tick < 0 else self.origin + tick / self.fps + self.one_way - 1e-9

    def obs_tick(self, t: float) -> int:
        """Tick whose observation is the latest the server holds at ``t`` (as Lookahead predicts)."""
        return math.floor((t - self.one_way - self.origin) * self.fps + 1e-9)

    def obs_at(self, t: float, queue: Queue) -> int:
        """Index of the latest observation the server will hold at ``t``."""
        tick = self.obs_tick(t)
        if tick < 0:
            return self.obs
        x = index_at(self.index, queue, tick)
        return x if x > self.obs else self.obs

    def arrival(self, t_done: float) -> int:
        """Tick from which a chunk finished at ``t_done`` is usable."""
        return math.ceil((t_done + self.one_way - self.origin) * self.fps - 1e-9)


def _with(queue: Queue, arrival: int, end: int) -> Queue:
    end0, pending = queue
    if arrival <= 0:
        return max(end0, end), pending
    return end0, tuple(sorted((*pending, (arrival, end))))


class RolloutScheduler(Scheduler):
    """Rollout over a short window with EDF as the base policy (see the module docstring).

    Args:
        profile / max_batch_size: as every scheduler.
        window_s: batches are simulated and executed time is scored until this long after the
            decision.
        tail: base policy after the first batch: ``due``, ``same`` or ``auto`` (by load).
        candidates: first batches rolled out per decision (at most).
        order: who comes first in the base policy's batches: ``deadline`` (EDF) or ``gain``
            (weighted coverage gain, see the module docstring).
        keep_plan: also roll out the plan kept from the last decision (module docstring, 4).
    """

    def __init__(
        self,
        profile: LatencyProfile,
        max_batch_size: int,
        window_s: float = 1.0,
        tail: str = "auto",
        candidates: int = 4,
        order: str = "deadline",
        keep_plan: bool = False,
    ) -> None:
        super().__init__(profile, max_batch_size)
        if not window_s > 0:
            raise ConfigError("scheduler.window_s", f"must be > 0, got {window_s}")
        if tail not in TAILS:
            raise ConfigError("scheduler.tail", f"must be one of {', '.join(TAILS)}, got {tail!r}")
        if candidates < 1:
            raise ConfigError("scheduler.candidates", f"must be >= 1, got {candidates}")
        if order not in ORDERS:
            raise ConfigError("scheduler.order", f"must be one of {', '.join(ORDERS)}, got {order!r}")
        self.window_s = window_s
        self.tail = tail
        self.candidates = candidates
        self.order = order
        self.keep_plan = keep_plan
        # The later batches of the rollout that won the last decision, by robot id: the next
        # decision rolls them out again as one more candidate (see select).
        self._plan: list[tuple[str, ...]] = []
        self.plans_kept = 0  # decisions where the kept plan's batch beat every fresh candidate's
        self._window = window_s

    # ---- the decision ----------------------------------------------------------------------

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        # Inf live; a finite offline episode may tell its end (Scheduler.episode_end_s).
        self._window = self.window_until(now, self.window_s)
        pool = [_Robot(k, r, now, self._window) for k, r in enumerate(robots) if r.obs_index is not None]
        useful = [r for r in pool if r.useful]
        if not useful:
            return []
        for i, r in enumerate(pool):
            r.i = i
        self._order = sorted(pool, key=lambda r: (r.deadline, r.k))
        # Each rollout starts from copies of these (lists by pool position: cheaper than dicts).
        self._ready0 = [r.ready for r in pool]
        self._deadline0 = [r.deadline for r in pool]
        if self.keep_plan:
            self._by_id = {r.mirror.spec.robot_id: r for r in pool}
        ranked = [r for r in self._order if r.useful]
        b = min(self.max_batch_size, len(useful))
        firsts = self._first_batches(useful, ranked, now, b)
        tail = self.tail
        if tail == "auto":
            # More robots due than one batch can hold: the throughput regime.
            limit = now + self.d_infer[b - 1] + self.d_infer[0]
            due_now = sum(1 for r in ranked if r.deadline < limit + r.one_way)
            tail = "same" if due_now > b else "due"
        best: list[_Robot] | None = None
        best_score = -math.inf
        best_plan: list[tuple[str, ...]] = []
        for first in firsts:
            score, plan = self._rollout(pool, first, now, tail)
            # Strictly better only: earlier candidates (smaller batches first among equals, see
            # _first_batches) win ties.
            if score > best_score + 1e-9:
                best, best_score, best_plan = first, score, plan
        assert best is not None
        if self.keep_plan and self._plan:
            # The plan kept from the last decision, replayed from where it stands: it wins ties,
            # so a decision never drops a plan for one that the rollout does not score higher
            # (rollout's improvement property: without it, re-deciding at every batch can
            # abandon a good plan halfway and end below the base policy).
            kept = self._scripted(self._plan[0], now)
            if kept:
                score, plan = self._rollout(pool, kept, now, tail, self._plan[1:])
                if score >= best_score - 1e-9:
                    self.plans_kept += {r.k for r in kept} != {r.k for r in best}
                    best, best_score, best_plan = kept, score, plan
        self._plan = best_plan
        return [r.mirror for r in best]

    def _scripted(self, ids: tuple[str, ...], t: float, ready: list[float] | None = None) -> list[_Robot]:
        """The robots of a planned batch that are still here and useful at ``t``."""
        by_id = self._by_id
        ready = self._ready0 if ready is None else ready
        out = []
        for rid in ids:
            r = by_id.get(rid)
            if r is not None and ready[r.i] <= t:
                out.append(r)
        return out

    def _first_batches(self, useful: list[_Robot], ranked: list[_Robot], now: float, b: int) -> list[list[_Robot]]:
        """Candidate first batches, best first by Lookahead's score, at most ``candidates``."""
        d = self.d_infer
        for r in useful:
            gains, memo = [], {}
            q0 = r.queue
            for s in range(1, b + 1):
                a = r.arrival(now + d[s - 1])
                if a not in memo:
                    if a >= r.ticks:
                        memo[a] = 0.0
                    else:
                        q = _with(q0, a, r.obs + r.h)
                        memo[a] = r.wpt * (index_at(r.index, q, r.ticks) - r.index - r.base)
                gains.append(memo[a])
            r.gains = gains
        by_size = []
        for s in range(1, b + 1):
            top = sorted(useful, key=lambda r: (-r.gains[s - 1], r.deadline, r.k))[:s]
            by_size.append((sum(r.gains[s - 1] for r in top) / d[s - 1], top))
        # Priority under the candidate budget: the due batch (what the optimum's small staggered
        # batches look like), Lookahead's own choice, its best single robot and pair, EDF's full
        # batch, then Lookahead's other batches by its score.
        by_score = [top for _, top in sorted(by_size, key=lambda c: -c[0])]
        ordered = [self._due(ranked, now, self._deadline0, b), by_score[0], by_size[0][1]]
        if b > 1:
            ordered.append(by_size[1][1])
        ordered.append(ranked[:b])
        ordered += by_score[1:]
        out: list[list[_Robot]] = []
        seen: set[tuple[int, ...]] = set()
        for batch in ordered:
            key = tuple(sorted(r.k for r in batch))
            if key not in seen:
                seen.add(key)
                out.append(batch)
            if len(out) == self.candidates:
                break
        # Among equal scores the smaller batch should win: it frees the device sooner.
        out.sort(key=len)
        return out

    def _due(self, ranked: list[_Robot], t: float, deadline: list[float], cap: int) -> list[_Robot]:
        """EDF, but only the robots that run dry before a chunk of the *next* batch could reach
        them (at best ``d_infer(s) + d_infer(1) + d_action`` from now); at least the first."""
        d = self.d_infer
        out: list[_Robot] = []
        for r in ranked:
            if len(out) == cap:
                break
            if deadline[r.i] < t + d[len(out)] + d[0] + r.one_way:
                out.append(r)
            elif self.order == "deadline":
                break  # sorted by deadline: nobody later is due either
            # order=gain: ``ranked`` is not sorted by deadline, so a later robot may still be due
        return out or ranked[:1]

    # ---- one rollout -----------------------------------------------------------------------

    def _rollout(
        self, pool: list[_Robot], first: list[_Robot], now: float, tail: str, script: Sequence[tuple[str, ...]] = ()
    ) -> tuple[float, list[tuple[str, ...]]]:
        """Weighted executed time the window gains by dispatching ``first``, then the batches of
        ``script`` (robot ids; those not useful by then are left out), then following the base
        policy ``tail`` (``due`` or ``same``) until the end of the window. Also returns the
        batches after ``first`` that it dispatched, by robot id."""
        d = self.d_infer
        end = now + self._window
        cap = self.max_batch_size
        queues: dict[int, Queue] = {}  # served robots' queues, by pool position
        ready = self._ready0[:]  # time from which each robot is useful (again), by pool position
        deadline = self._deadline0[:]
        batch = first
        t = now
        later: list[tuple[str, ...]] = []
        step = 0
        while True:
            t_done = t + d[len(batch) - 1]
            for r in batch:
                q = queues.get(r.i, r.queue)
                obs = r.obs_at(t, q)
                q = _with(q, r.arrival(t_done), obs + r.h)
                queues[r.i] = q
                deadline[r.i] = r.origin + dry_tick(r.index, q) / r.fps
                ready[r.i] = r.useful_from(tick_reaching(r.index, q, obs + r.hm))
            t = t_done
            if t >= end:
                break
            ranked = self._useful_at(t, ready, deadline)
            if not ranked:
                # Nobody useful: the device idles until the first robot's useful observation lands.
                t = self._next_useful(ready)
                if t >= end:
                    break
                ranked = self._useful_at(t, ready, deadline)
                if not ranked:
                    break
            batch = []
            while step < len(script) and not batch:
                batch = self._scripted(script[step], t, ready)
                step += 1
            if not batch:
                batch = self._due(ranked, t, deadline, cap) if tail == "due" else ranked[: len(first)]
            if self.keep_plan:
                later.append(tuple(r.mirror.spec.robot_id for r in batch))
        score = 0.0
        for i, q in queues.items():
            r = pool[i]
            score += r.wpt * (index_at(r.index, q, r.ticks) - r.index - r.base)
        return score, later

    def _next_useful(self, ready: list[float]) -> float:
        """Earliest time at which some robot is useful again."""
        return min(ready) + 2e-9

    def _useful_at(self, t: float, ready: list[float], deadline: list[float]) -> list[_Robot]:
        """Robots useful at epoch ``t``, in the base policy's ``order``."""
        if self.order == "gain":
            # A full batch dispatched at t lands at t + d(b) + one-way; the chunk covers until
            # its observation (about one-way before t) plus h. What it adds is the part past
            # both the landing and the robot's current coverage end (its deadline).
            lands = t + self.d_infer[self.max_batch_size - 1]
            keyed = []
            for r in self._order:
                i = r.i
                if ready[i] <= t:
                    dry, landed = deadline[i], lands + r.one_way
                    gain = t + r.span - (dry if dry > landed else landed)
                    keyed.append((-r.weight * gain if gain > 0 else 0.0, r.k, r))
        else:
            keyed = [(deadline[r.i], r.k, r) for r in self._order if ready[r.i] <= t]
        keyed.sort()  # by key, then robot index (unique: the robots themselves are never compared)
        return [c[2] for c in keyed]


@SchedulerConfig.register_subclass("rollout")
@dataclass
class RolloutConfig(SchedulerConfig):
    """Rollout knobs (weights come from each robot's registration, as for Lookahead).

    Attributes:
        window_s: simulate batches and score executed time until this long after the decision.
        tail: base policy after the first batch: ``auto`` (by load), ``due`` or ``same``.
        candidates: first batches rolled out per decision (at most).
        order: base policy's order within its batches: ``deadline`` (EDF) or ``gain``.
        keep_plan: keep the winning rollout's later batches and roll them out again at the next
            decision as one more candidate.
    """

    window_s: float = 1.0
    tail: str = "auto"
    candidates: int = 4
    order: str = "deadline"
    keep_plan: bool = False

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return RolloutScheduler(
            profile, max_batch_size, self.window_s, self.tail, self.candidates, self.order, self.keep_plan
        )

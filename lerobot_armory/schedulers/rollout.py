"""Rollout: score each candidate first batch by playing the mirror forward under a base policy.

Lookahead (docs/spec.md §3) scores a batch by what it adds inside a 1 s window, per GPU-second, one
epoch deep. That misses what the offline optimum (the study in ``research/armory_research/optimal.py``) exploits:
a batch decides *when the device is next free* and so shapes every later batch (small staggered
batches keep latency low while the fleet can be kept fed; full batches keep the throughput up
once it cannot), and it decides which robots are useful later. Rollout measures that directly:

1. **Candidates.** Lookahead's best batch of every size ``s`` (the ``s`` largest weighted
   marginal gains, so weights and the freshness of each robot's observation count), EDF's full
   batch, and the *due* batch (the robots that starve unless served now, :meth:`~RolloutScheduler._due`).
   They are ordered by Lookahead's score and at most ``CANDIDATES`` (4) are rolled out.
2. **Rollout.** Each candidate is dispatched on a copy of the fleet's mirror state, then a base
   policy (EDF ordering) plays on until ``window_s`` after the decision, predicting every later
   observation the way Lookahead does (the index the mirror says the robot holds ``d_obs``
   earlier). Two base policies, picked once per decision from the load (``auto``):

   - *due*: each later batch holds only the robots that would starve if left to the batch
     after it (at least one). It keeps batches as small as the fleet allows, which is what the
     optimum does while the fleet can be kept fed.
   - *same*: each later batch is the candidate's size, earliest deadlines first. Used when more
     robots are due than one batch holds (overload): the rollout then asks "what if I keep
     dispatching batches of this size", so a small first batch is charged for the throughput it
     would cost if repeated. (Scoring a small first batch followed by full batches is what made
     an early version pick small batches at every decision and lose throughput under overload.)

   ``auto`` was kept as the one rule after the offline study (``research/``, results in
   ``docs/results/frontier/README.md``): ``same`` alone is better on overloaded fleets, ``due``
   alone where the device can nearly keep the fleet fed (piper half-fast N = 4..5: 100 / 99.7 %
   of the best schedule found against 96.4 / 96.5 %), and the load test picks the right one.

3. **Score.** The fleet's weighted executed robot time in the window (docs/spec.md §2 reward, each
   robot's own weight). The best candidate is dispatched; ties go to the smaller batch.
4. **A shared device.** When other policies share the device (the
   :class:`~lerobot_armory.arbiter.PolicyArbiter` shows them as :attr:`Scheduler.peers`), the
   rollout plays the whole device: their robots are in the pool and scored, and after each batch
   the policy of the soonest deadline goes next (the arbiter's rule), a peer's batch chosen by
   the same base policies at its own ``d_infer``. And a robot left out of a batch must survive
   not only this policy's next batch but the longest batch another policy may run in between
   (the *gap* of :meth:`~RolloutScheduler._due`). Without both, a flat 10 ms ACT beside a π0.5
   served its robots one or two at a time, just in time (free on a device of its own), took
   38 % of the device in 1.8-robot batches where 8-robot ones cost the same, and its robots
   left out waited behind 87 ms π0.5 batches: the study's ``act-heavy`` N = 32 starved 7.97 %
   mixed against 1.55 % on a device split by demand, 0.62 % with both
   (docs/results/multi_policy/README.md). With one policy nothing changes, bit for bit.

The study also measured other orders inside the later batches (largest weighted coverage gain
first), rolling out the previous decision's plan again, and more candidates; none moved the
results enough to keep (``docs/results/frontier/README.md``, commit 8588e12), so they are not
knobs of the product.

Decisions depend on nothing but the mirror state, so they are deterministic and the same on
every machine; the cost is bounded by ``CANDIDATES`` × the window's epochs (SPEC budget:
≤ 1 ms p99 at N = 10, b = 5; ≤ 10 ms at N = 100, b = 8; see ``benchmarks/decision_time.py``
and ``research/benchmarks/frontier.py``). On a shared device a rollout plays every policy's
robots, so a decision costs about what one policy's of the whole fleet's size would.

Why it is fast enough. A rollout asks three things about a robot many times: its index at a
tick, when it runs dry, and when it becomes useful again. It keeps each robot in the mirror's
coverage-queue form (:data:`~lerobot_armory.transition.Queue`) and asks
:func:`~lerobot_armory.transition.index_at`, :func:`~lerobot_armory.transition.dry_tick` and
:func:`~lerobot_armory.transition.tick_reaching`: the transition specialised to such queues, which
lives (and is tested against :func:`~lerobot_armory.transition.advance`) in the mirror.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.transition import Queue, dry_tick, index_at, observed_tick, queue_of, queue_with, tick_of, tick_reaching
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig
from lerobot_armory.schedulers.dispatch_timing import next_observation_at

# First batches rolled out per decision (at most): the due batch, Lookahead's choice, its best
# single robot and pair; more did not change the study's results and cost a rollout each.
CANDIDATES = 4


class _Robot:
    """One robot frozen at the decision: its window view in rollout form plus fixed facts."""

    __slots__ = (
        "k", "mirror", "index", "queue", "origin", "fps", "one_way", "h", "hm", "wpt", "last", "obs",
        "ticks", "useful", "deadline", "base", "ready", "gains", "i", "g",
    )  # fmt: skip

    def __init__(self, k: int, mirror: RobotMirror, now: float, horizon_s: float, g: int = 0) -> None:
        view = mirror.window_view(now, horizon_s)
        spec = mirror.spec
        self.k = k
        self.g = g  # its policy: 0 this scheduler's, 1.. the peers' (Scheduler.peers), in order
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

    def useful_from(self, tick: int) -> float:
        """Server time from which the observation of ``tick`` is held (inf for tick -1: never)."""
        return math.inf if tick < 0 else self.origin + tick / self.fps + self.one_way - 1e-9

    def obs_at(self, t: float, queue: Queue) -> int:
        """Index of the latest observation the server will hold at ``t``."""
        tick = observed_tick(t, self.origin, self.fps, self.one_way)
        if tick < 0:
            return self.obs
        x = index_at(self.index, queue, tick)
        return x if x > self.obs else self.obs

    def arrival(self, t_done: float) -> int:
        """Tick from which a chunk finished at ``t_done`` is usable."""
        return tick_of(t_done + self.one_way, self.origin, self.fps)


class RolloutScheduler(Scheduler):
    """Rollout over a short window with EDF as the base policy (see the module docstring).

    Args:
        profile / max_batch_size: as every scheduler.
        window_s: batches are simulated and executed time is scored until this long after the
            decision.
    """

    def __init__(self, profile: LatencyProfile, max_batch_size: int, window_s: float = 1.0) -> None:
        super().__init__(profile, max_batch_size)
        if not window_s > 0:
            raise ConfigError("scheduler.window_s", f"must be > 0, got {window_s}")
        self.window_s = window_s
        # The last select()'s (now, pool, batch, score, tail): hold() re-rolls that batch later.
        self._decided: tuple | None = None
        # The last select()'s peer policies, (d_infer, cap, base policy, gap) each, index g - 1,
        # and this policy's gap (see _due).
        self._peer_rules: list[tuple[Sequence[float], int, str, float]] = []
        self._gap = 0.0

    # ---- the decision ----------------------------------------------------------------------

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        pool = [_Robot(k, r, now, self.window_s) for k, r in enumerate(robots) if r.obs_index is not None]
        useful = [r for r in pool if r.useful]
        if not useful:
            return []
        pool += self._peer_robots(len(robots), now)
        for i, r in enumerate(pool):
            r.i = i
        self._order = sorted(pool, key=lambda r: (r.deadline, r.k))
        # Each rollout starts from copies of these (lists by pool position: cheaper than dicts).
        self._ready0 = [r.ready for r in pool]
        self._deadline0 = [r.deadline for r in pool]
        # On a shared device another policy's batch may run between two of this policy's: the
        # longest batch of any other policy is the gap a robot left out of a batch must survive.
        longest = [self.d_infer[self.max_batch_size - 1]]
        longest += [p.d_infer[p.max_batch_size - 1] if p.robots else 0.0 for p in self.peers]
        gaps = [max((x for h, x in enumerate(longest) if h != g), default=0.0) for g in range(len(longest))]
        self._gap = gaps[0]
        ranked = [r for r in self._order if r.useful and r.g == 0]
        b = min(self.max_batch_size, len(useful))
        tail = self._tail(ranked, now, b)
        self._peer_rules = []
        for g, peer in enumerate(self.peers, 1):
            theirs = [r for r in self._order if r.useful and r.g == g]
            cap = peer.max_batch_size
            rule = self._tail(theirs, now, min(cap, len(theirs)), peer.d_infer) if theirs else "due"
            self._peer_rules.append((peer.d_infer, cap, rule, gaps[g]))
        best: list[_Robot] | None = None
        best_score = -math.inf
        for first in self._first_batches(useful, ranked, now, b):
            score = self._rollout(pool, first, now, tail)
            # Strictly better only: earlier candidates (smaller batches first among equals, see
            # _first_batches) win ties.
            if score > best_score + 1e-9:
                best, best_score = first, score
        assert best is not None
        self._decided = (now, pool, best, best_score, tail)
        return [r.mirror for r in best]

    # ---- dispatch timing -------------------------------------------------------------------

    def hold(self, robots: Sequence[RobotMirror], batch: Sequence[RobotMirror], now: float) -> float | None:
        """Rollout decides *when* with the same rollouts as *whom* (``--scheduler.wait_ms``).

        The chosen batch is rolled out again as if dispatched at each instant a member's next
        observation is predicted to land (within ``max_wait_s``), plus the margin (so the wait
        pays even if the dispatch happens that much later): the rollout then serves the fresher
        observations, idles the device until then and plays the same base policy after. The
        device waits for the best such instant only if its window score beats dispatching now.
        Unlike the generic rule (:func:`.timing.hold_until`), this sees what the wait costs the
        batches after it.
        """
        decided = self._decided
        if self.max_wait_s <= 0 or decided is None or decided[0] != now:
            return None
        _, pool, best, best_score, tail = decided
        if [r.mirror for r in best] != list(batch):
            return None
        end = now + self.window_s
        candidates = sorted({c for r in best if now < (c := next_observation_at(r.mirror)) <= now + self.max_wait_s})
        chosen, chosen_score = None, best_score
        for c in candidates:
            t = c + self.wait_margin_s
            score = self._rollout(pool, best, t, tail, end)
            if score > chosen_score + 1e-9:
                chosen, chosen_score = t, score
        return chosen

    def _peer_robots(self, k0: int, now: float) -> list[_Robot]:
        """The other policies' robots on this device (:attr:`Scheduler.peers`), in rollout form.

        Why: on a shared device this policy's next batch does not start when its batch ends; the
        others' batches run in between, and every device-second this policy spends is one they
        wait. Alone, a 10 ms ACT batch of one robot costs nothing its rollout could see; beside a
        π0.5 it costs the π0.5 robots that device time (docs/results/multi_policy). A peer robot
        whose mirror cannot be evaluated is left out (its own policy's dispatcher deals with it).
        """
        out: list[_Robot] = []
        for g, peer in enumerate(self.peers, 1):
            for mirror in peer.robots:
                if mirror.obs_index is None:
                    continue
                try:
                    out.append(_Robot(k0 + len(out), mirror, now, self.window_s, g))
                except Exception:  # noqa: BLE001 - another policy's broken robot: not this decision's
                    continue
        return out

    def _tail(self, ranked: list[_Robot], now: float, b: int, d: Sequence[float] | None = None) -> str:
        """The base policy for this decision's rollouts: ``same`` when more robots are due than
        one batch can hold (the throughput regime), else ``due`` (``d``: the policy's d_infer,
        this scheduler's by default)."""
        d = self.d_infer if d is None else d
        limit = now + d[b - 1] + d[0]
        due_now = sum(1 for r in ranked if r.deadline < limit + r.one_way)
        return "same" if due_now > b else "due"

    def _first_batches(self, useful: list[_Robot], ranked: list[_Robot], now: float, b: int) -> list[list[_Robot]]:
        """Candidate first batches, best first by Lookahead's score, at most ``CANDIDATES``."""
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
                        q = queue_with(q0, a, r.obs + r.h)
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
            if len(out) == CANDIDATES:
                break
        # Among equal scores the smaller batch should win: it frees the device sooner.
        out.sort(key=len)
        return out

    def _due(
        self,
        ranked: list[_Robot],
        t: float,
        deadline: list[float],
        cap: int,
        d: Sequence[float] | None = None,
        gap: float | None = None,
    ) -> list[_Robot]:
        """EDF, but only the robots that run dry before a chunk of the *next* batch could reach
        them (at best ``d_infer(s) + gap + d_infer(1) + d_action`` from now); at least the first.
        ``d``: the robots' policy's d_infer; ``gap``: the longest batch another policy may run
        in between (0 alone); both this scheduler's by default."""
        d = self.d_infer if d is None else d
        gap = self._gap if gap is None else gap
        out: list[_Robot] = []
        for r in ranked:
            if len(out) == cap:
                break
            if deadline[r.i] < t + d[len(out)] + gap + d[0] + r.one_way:
                out.append(r)
            else:
                break  # sorted by deadline: nobody later is due either
        return out or ranked[:1]

    # ---- one rollout -----------------------------------------------------------------------

    def _rollout(self, pool: list[_Robot], first: list[_Robot], now: float, tail: str, end: float | None = None) -> float:
        """Weighted executed time the window gains by dispatching ``first`` at ``now``, then
        following the base policy ``tail`` (``due`` or ``same``) until ``end`` (default: the
        window after ``now``; a timed dispatch passes the decision's window).

        With peers (other policies on the device) the rollout plays the whole device: after each
        batch the policy of the soonest deadline goes next (the arbiter's rule), a peer's batch
        chosen by its own base policy (``due``, or its full batch) at its own ``d_infer``, and
        every robot's executed time is scored."""
        d = self.d_infer
        end = now + self.window_s if end is None else end
        cap = self.max_batch_size
        peers = self._peer_rules
        queues: dict[int, Queue] = {}  # served robots' queues, by pool position
        ready = self._ready0[:]  # time from which each robot is useful (again), by pool position
        deadline = self._deadline0[:]
        batch = first
        t = now
        while True:
            t_done = t + (peers[batch[0].g - 1][0] if batch[0].g else d)[len(batch) - 1]
            for r in batch:
                q = queues.get(r.i, r.queue)
                obs = r.obs_at(t, q)
                q = queue_with(q, r.arrival(t_done), obs + r.h)
                queues[r.i] = q
                deadline[r.i] = r.origin + dry_tick(r.index, q) / r.fps
                ready[r.i] = r.useful_from(tick_reaching(r.index, q, obs + r.hm))
            t = t_done
            if t >= end:
                break
            ranked = self._useful_at(t, ready, deadline)
            if not ranked:
                # Nobody useful: the device idles until the first robot's useful observation lands.
                t = min(ready) + 2e-9
                if t >= end:
                    break
                ranked = self._useful_at(t, ready, deadline)
                if not ranked:
                    break
            if peers:
                g = ranked[0].g  # the policy of the soonest deadline goes next
                ranked = [r for r in ranked if r.g == g]
                if g:
                    d_g, cap_g, rule, gap_g = peers[g - 1]
                    batch = self._due(ranked, t, deadline, cap_g, d_g, gap_g) if rule == "due" else ranked[:cap_g]
                    continue
            batch = self._due(ranked, t, deadline, cap) if tail == "due" else ranked[: len(first)]
        score = 0.0
        for i, q in queues.items():
            r = pool[i]
            score += r.wpt * (index_at(r.index, q, r.ticks) - r.index - r.base)
        return score

    def _useful_at(self, t: float, ready: list[float], deadline: list[float]) -> list[_Robot]:
        """Robots useful at epoch ``t``, earliest deadline first (then registration order)."""
        keyed = [(deadline[r.i], r.k, r) for r in self._order if ready[r.i] <= t]
        keyed.sort()  # by key, then robot index (unique: the robots themselves are never compared)
        return [c[2] for c in keyed]


@SchedulerConfig.register_subclass("rollout")
@dataclass
class RolloutConfig(SchedulerConfig):
    """Rollout's knob (weights come from each robot's registration, as for Lookahead).

    Attributes:
        window_s: simulate batches and score executed time until this long after the decision.
    """

    window_s: float = 1.0

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return RolloutScheduler(profile, max_batch_size, self.window_s)

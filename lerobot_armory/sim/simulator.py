"""Discrete-event fleet simulator: the real mirror and schedulers, driven by simulated time.

The world has two views of every robot:

- the *ground truth*, a :class:`~lerobot_armory.mirror.RobotTimeline` with the chunks' true
  arrival times (network delays drawn per request);
- the *server's mirror*, a :class:`~lerobot_armory.mirror.RobotMirror` fed only with what a
  server could know: observations when they arrive (index + robot-clock capture time), and
  execution reports (when a chunk reached the robot, robot clock). Robot clocks are offset from
  the server's by a random amount, so the mirror's delay estimation is exercised honestly.

Both move through the same transition (:func:`~lerobot_armory.transition.advance`). Events are
"the GPU becomes free" and, while the GPU idles, "an observation arrives"; the robots' ticks
between events are advanced in bulk, which keeps 10 robots × 300 s well under a second of
simulation for RR and EDF.

Several policies may share the device (a mixed fleet): each has its own scheduler (and so its own
``d_infer(b)`` and batch cap), every batch holds one policy's robots and takes that policy's
``d_infer``, and a :class:`~lerobot_armory.arbiter.PolicyArbiter` picks whose batch runs next.
One policy goes through the same arbiter, which then plans exactly as that policy's dispatcher.
"""

from __future__ import annotations

import heapq
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from lerobot_armory.arbiter import DEFAULT_POLICY, PolicyArbiter
from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.dispatch import Dispatcher
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.delay import DelayEstimator
from lerobot_armory.mirror import RobotMirror, RobotTimeline
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.transition import Chunk
from lerobot_armory.schedulers.base import Scheduler

# Robot clocks differ from the server's by up to this much (seconds); nothing may depend on it.
MAX_CLOCK_OFFSET_S = 0.5
# Compare the mirror's predicted index with the truth at every this many decisions.
FIDELITY_EVERY = 8


@dataclass
class RobotResult:
    """Ground-truth outcome for one robot."""

    robot_id: str
    tier: str
    weight: float
    fps: float
    ticks: int
    executed_steps: int
    chunks_received: int
    first_executed_index: Counter = field(default_factory=Counter)  # offset -> count; "unused"
    policy: str = DEFAULT_POLICY

    @property
    def starved_steps(self) -> int:
        return self.ticks - self.executed_steps

    @property
    def starvation_pct(self) -> float:
        return 100.0 * self.starved_steps / self.ticks if self.ticks else 0.0

    @property
    def executed_s(self) -> float:
        return self.executed_steps / self.fps


@dataclass(frozen=True)
class BatchTrace:
    """One batch the device ran (kept only when the simulator is asked to ``trace``)."""

    policy: str
    t_start: float
    t_done: float
    robot_ids: tuple[str, ...]


@dataclass
class SimResult:
    """Everything one simulated run measured."""

    robots: list[RobotResult]
    batch_sizes: Counter
    decision_s: list[float]
    duration_s: float
    mirror_index_error: list[int]  # |predicted - true| index at every decision, for fidelity checks
    held_s: float = 0.0  # time the device waited on purpose (dispatch timing, ``wait_ms``)
    decision_cpu_s: list[float] = field(default_factory=list)  # the decisions' CPU (thread) time
    policy_batch_sizes: dict[str, Counter] = field(default_factory=dict)  # per policy, as batch_sizes
    device_s: dict[str, float] = field(default_factory=dict)  # device time each policy's batches took
    batches: list[BatchTrace] = field(default_factory=list)  # every batch, when traced

    @property
    def avg_starvation_pct(self) -> float:
        return float(np.mean([r.starvation_pct for r in self.robots]))

    @property
    def policies(self) -> list[str]:
        """The policies that served the fleet (one, ``default``, for a one-scheduler fleet)."""
        return list(self.policy_batch_sizes) or [DEFAULT_POLICY]

    def policy_starvation_pct(self, policy: str, tier: str | None = None) -> float:
        """Mean starvation of ``policy``'s robots (of one tier, if given); NaN if it has none."""
        rows = [r for r in self.robots if r.policy == policy and (tier is None or r.tier == tier)]
        return float(np.mean([r.starvation_pct for r in rows])) if rows else float("nan")

    def tier(self, tier: str) -> list[RobotResult]:
        return [r for r in self.robots if r.tier == tier]

    def tier_starvation_pct(self, tier: str) -> float:
        rows = self.tier(tier)
        return float(np.mean([r.starvation_pct for r in rows])) if rows else float("nan")

    @property
    def executed_s(self) -> float:
        return sum(r.executed_s for r in self.robots)

    @property
    def weighted_executed_s(self) -> float:
        return sum(r.weight * r.executed_s for r in self.robots)

    def decision_ms(self, q: float) -> float:
        return float(np.percentile(self.decision_s, q) * 1000) if self.decision_s else 0.0

    def decision_cpu_ms(self, q: float) -> float:
        """Percentile ``q`` of the decisions' CPU time (the scheduler's own cost), ms."""
        return float(np.percentile(self.decision_cpu_s, q) * 1000) if self.decision_cpu_s else 0.0

    def first_executed_index(self) -> Counter:
        total: Counter = Counter()
        for r in self.robots:
            total.update(r.first_executed_index)
        return total


class FleetSimulator:
    """Simulates one fleet served by one scheduler.

    Args:
        specs: the robots.
        scheduler: any registered scheduler (the object the live server would run), or one per
            policy by name when several policies share the device (then ``policy_of`` says
            which serves each robot).
        duration_s: simulated seconds.
        uplink / downlink: one-way delay models, drawn per request.
        seed: seeds the network draws, tick phases and clock offsets.
        true_latency: how long batches really take, when that differs from the profile the
            scheduler plans with (e.g. a live server's measured per-batch overhead added);
            default: the scheduler's profile.
        warmup_s: ticks before this time are not scored (``ticks`` and ``executed_steps`` count
            from the first tick at or after it): a steady-state measurement without the cold
            start. Nothing is told to the scheduler: it runs the same either way.
        policy_of: robot id -> policy name, required with several schedulers.
        trace: keep every batch in :attr:`SimResult.batches` (tests; costs memory on long runs).
    """

    def __init__(
        self,
        specs: Sequence[RobotSpec],
        scheduler: Scheduler,
        duration_s: float,
        uplink: LogNormalDelay,
        downlink: LogNormalDelay,
        seed: int = 0,
        true_latency: LatencyProfile | None = None,
        warmup_s: float = 0.0,
        policy_of: Mapping[str, str] | None = None,
        trace: bool = False,
    ) -> None:
        if not specs:
            raise ConfigError("robots", "the fleet is empty")
        if not duration_s > 0:
            raise ConfigError("duration_s", f"must be > 0, got {duration_s}")
        if len({s.robot_id for s in specs}) != len(specs):
            raise ConfigError("robots", "robot ids must be unique")
        if not 0 <= warmup_s < duration_s:
            raise ConfigError("warmup_s", f"must be in [0, duration_s), got {warmup_s}")
        self.warmup_s = warmup_s
        self.specs = list(specs)
        self.schedulers, self.policy = _policies(self.specs, scheduler, policy_of)
        if true_latency is not None and len(self.schedulers) > 1:
            raise ConfigError("true_latency", "a true latency profile is for one policy; several were given")
        self.trace = trace
        self.duration_s = duration_s
        self.uplink = uplink
        self.downlink = downlink
        self.rng = np.random.default_rng(seed)
        self.true_latency = true_latency

    def run(self) -> SimResult:
        """Run the whole duration and return the measurements."""
        rng, T = self.rng, self.duration_s
        n = len(self.specs)
        phase = [rng.uniform(0.0, 1.0 / s.fps) for s in self.specs]
        offset = [rng.uniform(-MAX_CLOCK_OFFSET_S, MAX_CLOCK_OFFSET_S) for _ in self.specs]  # server - robot
        n_ticks = [max(0, int(np.ceil((T - phase[j]) * s.fps - 1e-9))) for j, s in enumerate(self.specs)]
        warm_tick = [max(0, int(np.ceil((self.warmup_s - phase[j]) * s.fps - 1e-9))) for j, s in enumerate(self.specs)]
        warm_index: list[int | None] = [None] * n

        # Observation k of robot j is captured at its tick k and reaches the server at obs_arr[j][k].
        # The latest observation the server holds at t is the largest k with obs_arr <= t; a
        # suffix minimum makes that one binary search even when jitter reorders arrivals.
        obs_arr, suffix_min, sorted_arr = [], [], []
        for j, s in enumerate(self.specs):
            arr = phase[j] + np.arange(n_ticks[j]) / s.fps + self.uplink.sample(rng, n_ticks[j])
            obs_arr.append(arr)
            suffix_min.append(np.minimum.accumulate(arr[::-1])[::-1])
            sorted_arr.append(np.sort(arr))

        truth = [RobotTimeline(s.fps, phase[j]) for j, s in enumerate(self.specs)]
        mirrors = [RobotMirror(s, DelayEstimator()) for s in self.specs]
        for j, m in enumerate(mirrors):  # registration: one NTP-style exchange before the run
            t0, up, down = -1.0, self.uplink.sample(rng), self.downlink.sample(rng)
            m.estimator.add_exchange(t0 - offset[j], t0 + up, t0 + up, t0 + up + down - offset[j])

        results = [
            RobotResult(s.robot_id, s.tier, s.weight, s.fps, n_ticks[j] - warm_tick[j], 0, 0, policy=self.policy[j])
            for j, s in enumerate(self.specs)
        ]
        used: list[set[int]] = [set() for _ in self.specs]

        def on_use_for(j: int):
            def on_use(chunk: Chunk, first_offset: int) -> None:
                if chunk.chunk_id not in used[j]:
                    used[j].add(chunk.chunk_id)
                    results[j].first_executed_index[str(first_offset)] += 1

            return on_use

        hooks = [on_use_for(j) for j in range(n)]
        fed_tick = [-1] * n
        position = {s.robot_id: j for j, s in enumerate(self.specs)}
        # Each policy's robots, in registration order: the arbiter plans among one policy's.
        by_policy = {name: [m for j, m in enumerate(mirrors) if self.policy[j] == name] for name in self.schedulers}
        arbiter = PolicyArbiter({name: Dispatcher(s) for name, s in self.schedulers.items()})
        reports: list[tuple[float, int, int, float]] = []  # heap of (server receipt, robot, chunk id, arrival robot clock)
        batch_sizes: Counter = Counter()
        policy_batch_sizes: dict[str, Counter] = {name: Counter() for name in self.schedulers}
        device_s = dict.fromkeys(self.schedulers, 0.0)
        batches: list[BatchTrace] = []
        decision_s: list[float] = []
        decision_cpu_s: list[float] = []
        index_error: list[int] = []
        d_infer = {name: s.d_infer for name, s in self.schedulers.items()}
        if self.true_latency is not None:
            ((name, only),) = self.schedulers.items()
            d_infer[name] = self.true_latency.table_s(only.max_batch_size)

        def run_truth(j: int, k: int) -> None:
            # The scored window starts at the warm-up's tick: note the index there on the way.
            if warm_index[j] is None and k >= warm_tick[j]:
                truth[j].run_to(warm_tick[j], hooks[j])
                warm_index[j] = truth[j].index
            truth[j].run_to(k, hooks[j])

        def sync(t: float) -> None:
            """Deliver to the mirrors everything that reached the server by time t."""
            while reports and reports[0][0] <= t:
                recv, j, chunk_id, arrival_robot = heapq.heappop(reports)
                mirrors[j].on_report(chunk_id, arrival_robot, recv)
            for j in range(n):
                k = int(np.searchsorted(suffix_min[j], t, side="right")) - 1
                if k > fed_tick[j]:
                    k = int(k if obs_arr[j][k] <= t else _latest_arrived(obs_arr[j], k, t))
                    run_truth(j, k)
                    fed_tick[j] = k
                    capture_robot = phase[j] + k / self.specs[j].fps - offset[j]
                    mirrors[j].on_observation(truth[j].index, capture_robot, float(obs_arr[j][k]))

        t = 0.0
        while t < T:
            sync(t)
            if arbiter.has_work(by_policy):
                if len(decision_s) % FIDELITY_EVERY == 0:  # mirror fidelity: predicted vs true index
                    for j, m in enumerate(mirrors):
                        truth_now = truth[j].index + _executed_between(truth[j], t)
                        index_error.append(abs(m.predicted_index(t) - truth_now))
                picked = arbiter.plan(by_policy, t)
                assert picked is not None
                policy, plan = picked
                decision_s.append(plan.decision_s)
                decision_cpu_s.append(plan.decision_cpu_s)
                if plan.wait_until is not None:
                    # Dispatch timing: plan again when the wait ends or any observation lands.
                    t = min(plan.wait_until, _next_arrival(sorted_arr, t))
                    continue
                batch_sizes[plan.size] += 1
                policy_batch_sizes[policy][plan.size] += 1
                t_done = t + d_infer[policy][plan.size - 1]
                device_s[policy] += t_done - t
                if self.trace:
                    batches.append(BatchTrace(policy, t, t_done, tuple(plan.robot_ids)))
                arbiter.complete(policy, plan, t_done)
                for req in plan.requests:
                    j, chunk = position[req.robot_id], req.chunk
                    arrival = t_done + float(self.downlink.sample(rng))
                    truth[j].add_chunk(Chunk(chunk.chunk_id, chunk.i_start, chunk.h, arrival))
                    if arrival < T:
                        results[j].chunks_received += 1
                    report_recv = arrival + float(self.uplink.sample(rng))
                    heapq.heappush(reports, (report_recv, j, chunk.chunk_id, arrival - offset[j]))
                t = t_done
            else:
                # GPU idle, nobody useful: jump to the next observation arrival.
                t = _next_arrival(sorted_arr, t)
                if t == np.inf:
                    break

        for j, tl in enumerate(truth):
            run_truth(j, n_ticks[j])
            results[j].executed_steps = tl.index - (warm_index[j] or 0)
            unused = results[j].chunks_received - len(used[j])
            if unused > 0:
                results[j].first_executed_index["unused"] += unused
        held_s = sum(d.held_s for d in arbiter.dispatchers.values())
        return SimResult(
            results, batch_sizes, decision_s, T, index_error, held_s, decision_cpu_s,
            policy_batch_sizes, device_s, batches,
        )  # fmt: skip


def _policies(
    specs: Sequence[RobotSpec], scheduler: Scheduler | Mapping[str, Scheduler], policy_of: Mapping[str, str] | None
) -> tuple[dict[str, Scheduler], list[str]]:
    """The schedulers by policy and each robot's policy (position by position), checked."""
    if not isinstance(scheduler, Mapping):
        return {DEFAULT_POLICY: scheduler}, [DEFAULT_POLICY] * len(specs)
    if not scheduler:
        raise ConfigError("policies", "no policy given")
    if policy_of is None:
        raise ConfigError("policies", "several policies need policy_of (robot id -> policy name)")
    policy = []
    for s in specs:
        name = policy_of.get(s.robot_id)
        if name not in scheduler:
            raise ConfigError("policy", f"robot {s.robot_id}: policy {name!r} is not one of {', '.join(scheduler)}")
        policy.append(name)
    return dict(scheduler), policy


def _next_arrival(sorted_arr: list[np.ndarray], t: float) -> float:
    """The first observation arrival of any robot strictly after ``t`` (inf: none left)."""
    nxt = [sa[i] for sa in sorted_arr if (i := int(np.searchsorted(sa, t, side="right"))) < len(sa)]
    return float(min(nxt)) if nxt else float(np.inf)


def _latest_arrived(arr: np.ndarray, k: int, t: float) -> int:
    """Largest index <= k whose arrival is <= t (the suffix minimum guarantees one exists)."""
    while arr[k] > t:
        k -= 1
    return k


def _executed_between(tl: RobotTimeline, t: float) -> int:
    """Steps the ground-truth robot executes from its current tick up to time t (no side effects)."""
    probe = RobotTimeline(tl.fps, tl.anchor, tl.index, tl.tick, list(tl.chunks))
    return probe.run_to(probe.ticks_before(t))

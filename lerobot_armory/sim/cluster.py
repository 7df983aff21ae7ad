"""Multi-GPU fleet simulation: place robots on K replicas, then simulate every replica.

Robots join in a seeded random order (a shuffle of the fleet) and are placed one by one with a
placement policy (:mod:`lerobot_armory.placement`, the same objects the cluster's front uses) over
K replicas; each replica is one GPU with its own ``d_infer(b)`` table, batch cap and scheduler.
Then each replica's robots are simulated with the single-GPU
:class:`~lerobot_armory.sim.simulator.FleetSimulator` and a fresh scheduler.

**Replicas are independent once placed**: a robot talks to one replica only, replicas share no
device and no scheduler state, so a cluster of K replicas is exactly K single-GPU simulations
(what is *not* modelled: robots joining while others run, rebalancing moves, a shared network
bottleneck in front of the replicas).

**Distinct compositions.** Many replicas of a large cluster hold the same robots up to their ids
(e.g. "2 fast + 2 slow libero robots on an L40S"). With ``distinct_only=True`` (the default, and
what ``lerobot-armory-plan`` uses) each distinct composition is simulated once per seed, with the
run's seed, and its outcome is reused for every replica that has it (and, through ``cache``,
across cluster sizes K). The fleet-level starvation is an unbiased estimate either way, but
replicas with the same composition then share one draw of the network and tick phases, so the
*worst replica* is less extreme than with ``distinct_only=False``, where every replica is
simulated with its own seed (what ``benchmarks/cluster_placement.py`` uses).
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Mapping, MutableMapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.robot_spec import TIERS, RobotSpec
from lerobot_armory.placement import NoReplica, ReplicaView, make_placement, place_all
from lerobot_armory.sim.fleet_file import Fleet
from lerobot_armory.sim.simulator import FleetSimulator

# A composition: the sorted timing/weight/tier (and, when several policies share each GPU, the
# policy) of a replica's robots, ids dropped.
Composition = tuple[tuple[str, float, int, int, int, float, str | None], ...]
# Per-robot (tier, policy or None, starved steps, ticks) of one simulated composition, in its order.
Outcome = tuple[tuple[str, str | None, int, int], ...]


@dataclass
class ReplicaResult:
    """One replica (GPU) of a simulated cluster.

    Attributes:
        replica_id: its name (``gpu00``...).
        profile: its latency profile.
        robot_ids: the robots placed on it.
        tier_robots: robots per tier.
        predicted_utilization: the placement model's utilization (1 = device busy all the time).
        starved / ticks: per tier, starved control ticks and all ticks of its robots.
        simulated: False when its outcome was reused from an identical composition.
        policy_starved / policy_ticks: the same per (policy, tier), when several policies share
            the GPU (empty otherwise).
    """

    replica_id: str
    profile: str
    robot_ids: list[str]
    tier_robots: dict[str, int]
    predicted_utilization: float
    starved: dict[str, int] = field(default_factory=dict)
    ticks: dict[str, int] = field(default_factory=dict)
    simulated: bool = True
    policy_starved: dict[tuple[str, str], int] = field(default_factory=dict)
    policy_ticks: dict[tuple[str, str], int] = field(default_factory=dict)

    @property
    def robots(self) -> int:
        return len(self.robot_ids)

    def tier_starvation_pct(self, tier: str) -> float:
        """Starved ticks / all ticks of the tier's robots here, in % (NaN without such robots)."""
        ticks = self.ticks.get(tier, 0)
        return 100.0 * self.starved.get(tier, 0) / ticks if ticks else math.nan


@dataclass
class ClusterResult:
    """A simulated cluster: the placement and every replica's outcome.

    Attributes:
        placement: the placement policy's name.
        gpus: K.
        seed: the run's seed (join order, random placement, simulation).
        duration_s: simulated seconds per replica.
        replicas: per replica, in id order.
        wall_s: wall time of placement plus simulation.
        simulations: single-GPU simulations actually run (the rest were reused).
    """

    placement: str
    gpus: int
    seed: int
    duration_s: float
    replicas: list[ReplicaResult]
    wall_s: float
    simulations: int

    def tier_starvation_pct(self, tier: str) -> float:
        """Total starved ticks / total ticks over the tier's robots, in % (NaN without such robots)."""
        ticks = sum(r.ticks.get(tier, 0) for r in self.replicas)
        return 100.0 * sum(r.starved.get(tier, 0) for r in self.replicas) / ticks if ticks else math.nan

    @property
    def policies(self) -> list[str]:
        """The policies whose robots it served, when several share each GPU (empty otherwise)."""
        return sorted({p for r in self.replicas for p, _ in r.policy_ticks})

    def policy_tier_starvation_pct(self, policy: str, tier: str) -> float:
        """Starvation of ``policy``'s robots of ``tier`` over every replica, in % (NaN without such robots)."""
        ticks = sum(r.policy_ticks.get((policy, tier), 0) for r in self.replicas)
        starved = sum(r.policy_starved.get((policy, tier), 0) for r in self.replicas)
        return 100.0 * starved / ticks if ticks else math.nan

    def worst_replica_pct(self, tier: str = "fast") -> float:
        """The highest starvation of ``tier`` on any one replica (NaN without such robots)."""
        values = [r.tier_starvation_pct(tier) for r in self.replicas if r.ticks.get(tier)]
        return max(values) if values else math.nan

    @property
    def utilizations(self) -> list[float]:
        return [r.predicted_utilization for r in self.replicas]

    @property
    def robots_per_replica(self) -> list[int]:
        return [r.robots for r in self.replicas]

    def record(self) -> dict[str, Any]:
        """JSON summary (per replica: robots, tiers, utilization, starvation)."""
        return {
            "placement": self.placement,
            "gpus": self.gpus,
            "seed": self.seed,
            "duration_s": self.duration_s,
            "tiers": {t: _num(self.tier_starvation_pct(t)) for t in TIERS},
            "policies": {
                p: {t: _num(self.policy_tier_starvation_pct(p, t)) for t in TIERS} for p in self.policies
            },
            "worst_replica_fast_pct": _num(self.worst_replica_pct("fast")),
            "max_predicted_utilization": max(self.utilizations),
            "wall_s": self.wall_s,
            "simulations": self.simulations,
            "replicas": [
                {
                    "replica_id": r.replica_id,
                    "profile": r.profile,
                    "robots": r.robots,
                    "tier_robots": r.tier_robots,
                    "predicted_utilization": round(r.predicted_utilization, 4),
                    "starvation_pct": {t: _num(r.tier_starvation_pct(t)) for t in TIERS if r.ticks.get(t)},
                }
                for r in self.replicas
            ],
        }


def _num(x: float) -> float | None:
    return None if math.isnan(x) else x


def join_order(fleet: Fleet, seed: int) -> list[RobotSpec]:
    """The fleet's robots in the order they join: a shuffle seeded by ``seed``."""
    specs = fleet.specs()
    random.Random(seed).shuffle(specs)
    return specs


def place_fleet(
    fleet: Fleet, gpus: int, placement: str = "mirror_aware", seed: int = 0, profiles: Sequence[str] | None = None
) -> list[ReplicaView]:
    """Place the fleet (joining in its seeded order) on ``gpus`` replicas; returns the replica views.

    ``profiles`` gives each replica its own latency profile (heterogeneous GPUs); default: every
    replica runs the fleet's profile. When several policies share each GPU (a mixed fleet), every
    replica serves every policy, and each robot is charged its own policy's cost.
    """
    if not isinstance(gpus, int) or gpus < 1:
        raise ConfigError("gpus", f"must be an integer >= 1, got {gpus!r}")
    if profiles is not None and len(profiles) != gpus:
        raise ConfigError("profiles", f"need one latency profile per GPU ({gpus}), got {len(profiles)}")
    if profiles is not None and fleet.is_mixed:
        raise ConfigError("profiles", f"{fleet.source} names each policy's profile; one profile per GPU does not apply")
    names = list(profiles) if profiles is not None else [fleet.latency_profile] * gpus
    capacities = {name: fleet.capacity(name) for name in set(names)}
    capacity_of = fleet.capacity_of()  # one object for every view: placement memoizes on it
    limit = fleet.max_robots_per_gpu or fleet.robots
    width = max(2, len(str(gpus - 1)))
    replicas = [
        ReplicaView(f"gpu{k:0{width}d}", capacities[names[k]], max_robots=limit, capacity_of=capacity_of)
        for k in range(gpus)
    ]
    try:
        place_all(join_order(fleet, seed), replicas, make_placement(placement, seed))
    except NoReplica:
        raise ConfigError(
            "max_robots_per_gpu", f"{gpus} GPU(s) of at most {limit} robots cannot hold {fleet.robots} robots"
        ) from None
    return replicas


def composition(specs: Sequence[RobotSpec], policy_of: Mapping[str, str] | None = None) -> Composition:
    """A replica's robots without their ids, sorted (replicas with equal compositions behave alike);
    ``policy_of`` (robot id -> policy) when several policies share the GPU."""
    rows = [
        (s.tier, s.fps, s.chunk_size, s.h_min, s.h_max, s.weight, policy_of[s.robot_id] if policy_of else None)
        for s in specs
    ]
    return tuple(sorted(rows, key=lambda row: (row[:6], row[6] or "")))


def simulate_composition(
    comp: Composition, fleet: Fleet, profile: LatencyProfile, duration_s: float, seed: int
) -> Outcome:
    """Simulate one replica holding ``comp`` (canonical ids ``r0000``...) with fresh schedulers
    (one per policy, arbitrated, when several policies share the GPU)."""
    specs = [
        RobotSpec(f"r{k:04d}", fps, h, h_min, h_max, w, tier)
        for k, (tier, fps, h, h_min, h_max, w, _) in enumerate(comp)
    ]
    net = fleet.network()
    if fleet.is_mixed:
        schedulers = {p.name: fleet.scheduler.make(p.profile(), p.max_batch_size) for p in fleet.policies}
        policy_of = {s.robot_id: str(row[6]) for s, row in zip(specs, comp)}
        sim = FleetSimulator(specs, schedulers, duration_s, net, net, seed, policy_of=policy_of)
    else:
        scheduler = fleet.scheduler.make(profile, fleet.max_batch_size)  # one per replica: schedulers keep state
        sim = FleetSimulator(specs, scheduler, duration_s, net, net, seed)
    result = sim.run()
    return tuple((r.tier, row[6], r.starved_steps, r.ticks) for r, row in zip(result.robots, comp, strict=True))


def simulate_cluster(
    fleet: Fleet,
    gpus: int,
    placement: str = "mirror_aware",
    seed: int = 0,
    duration_s: float = 30.0,
    profiles: Sequence[str] | None = None,
    distinct_only: bool = True,
    cache: MutableMapping[Any, Outcome] | None = None,
) -> ClusterResult:
    """Place ``fleet`` on ``gpus`` replicas with ``placement`` and simulate every replica.

    Args:
        fleet: the robots and what serves them.
        gpus: K, the number of replicas.
        placement: ``random``, ``round_robin``, ``least_loaded`` or ``mirror_aware``.
        seed: seeds the join order, random placement and the simulations.
        duration_s: simulated seconds per replica.
        profiles: one latency profile per replica (heterogeneous GPUs); default: the fleet's.
        distinct_only: simulate each distinct replica composition once per seed (see the module
            docstring); False simulates every replica with its own seed.
        cache: outcomes of compositions already simulated, shared across calls (e.g. across K);
            only used with ``distinct_only``.
    """
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError("duration_s", f"must be > 0, got {duration_s}")
    start = time.perf_counter()
    replicas = place_fleet(fleet, gpus, placement, seed, profiles)
    names = list(profiles) if profiles is not None else [fleet.latency_profile] * gpus
    loaded = {name: fleet.profile(name) for name in set(names)}
    policy_of = fleet.policy_of() if fleet.is_mixed else None
    local: dict[Any, Outcome] = {}
    memo = cache if cache is not None else local
    runs = 0
    results = []
    for k, view in enumerate(replicas):
        specs = list(view.robots.values())
        tier_robots = {t: sum(s.tier == t for s in specs) for t in TIERS if any(s.tier == t for s in specs)}
        out = ReplicaResult(view.replica_id, names[k], [s.robot_id for s in specs], tier_robots, view.utilization())
        if specs:
            comp = composition(specs, policy_of)
            if distinct_only:
                key = (
                    comp,
                    names[k],
                    fleet.max_batch_size,
                    repr(fleet.scheduler),
                    fleet.policies,
                    fleet.net_median_ms,
                    fleet.net_sigma,
                    duration_s,
                    seed,
                )
                outcome = memo.get(key)
                out.simulated = outcome is None
                if outcome is None:
                    outcome = memo[key] = simulate_composition(comp, fleet, loaded[names[k]], duration_s, seed)
                    runs += 1
            else:
                # Its own seed per replica: independent network draws and tick phases.
                outcome = simulate_composition(comp, fleet, loaded[names[k]], duration_s, seed * 1_000_003 + k + 1)
                runs += 1
            for tier, policy, starved, ticks in outcome:
                out.starved[tier] = out.starved.get(tier, 0) + starved
                out.ticks[tier] = out.ticks.get(tier, 0) + ticks
                if policy is not None:
                    out.policy_starved[(policy, tier)] = out.policy_starved.get((policy, tier), 0) + starved
                    out.policy_ticks[(policy, tier)] = out.policy_ticks.get((policy, tier), 0) + ticks
        results.append(out)
    return ClusterResult(placement, gpus, seed, duration_s, results, time.perf_counter() - start, runs)

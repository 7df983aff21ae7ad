"""Which GPU serves which robot: the predicted load of a replica, and the placement policies.

Pure and deterministic like the mirror and the schedulers: no I/O, no clock. The cluster's front
(:mod:`lerobot_armory.entrypoints.cluster.front`) places live robots with it; the multi-replica simulator
(:mod:`lerobot_armory.sim.cluster`) places simulated ones with the same objects.

The load model is the mirror's timing, summed. A robot executes at most ``h_max`` actions of a
chunk at ``fps``; a chunk reaches it ``L`` seconds after the observation it answers (one full batch and two network
crossings; waiting for the device is what utilization above 1 means). So the robot
must be served at least every ``h_max / fps - L`` seconds (never more often than ``h_min / fps``,
the mirror's rule), and each chunk costs ``d_infer(b) / b`` device seconds at the replica's batch
cap ``b``. The robot's *demand* is that cost over that period, in device seconds per second; a
replica's predicted *utilization* is the sum over its robots. Above 1 the replica cannot serve
every robot on time and someone starves; the fast tier's short horizons make its robots the
heaviest.
"""

from __future__ import annotations

import abc
import functools
import itertools
import random
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import RobotSpec

# A robot's period is never taken shorter than one control tick: a robot whose horizon is shorter
# than the round trip cannot be kept fed by any placement, and its demand is capped at "every tick".
MIN_PERIOD_TICKS = 1.0


@dataclass(frozen=True)
class Capacity:
    """What one replica can serve: its ``d_infer(b)`` table and the network its robots cross.

    Attributes:
        latency_s: ``d_infer(b)`` in seconds for b = 1..max_batch_size.
        one_way_s: typical one-way network delay to the robots, seconds.
    """

    latency_s: tuple[float, ...]
    one_way_s: float = 0.00375

    def __post_init__(self) -> None:
        if not self.latency_s or any(not d > 0 for d in self.latency_s):
            raise ConfigError("latency_profile", f"d_infer(b) must be > 0 for every b, got {list(self.latency_s)}")
        if not self.one_way_s >= 0:
            raise ConfigError("one_way_s", f"must be >= 0, got {self.one_way_s}")

    @property
    def max_batch_size(self) -> int:
        return len(self.latency_s)

    @property
    def chunk_cost_s(self) -> float:
        """Device seconds one chunk costs in a full batch."""
        return self.latency_s[-1] / self.max_batch_size

    @property
    def round_trip_s(self) -> float:
        """Observation to chunk in the robot's hands: one full batch and two network crossings."""
        return self.latency_s[-1] + 2 * self.one_way_s


@functools.lru_cache(maxsize=65536)  # specs and capacities are frozen; a fleet has few distinct ones
def demand(spec: RobotSpec, capacity: Capacity) -> float:
    """Device seconds per second ``spec`` needs from a replica of ``capacity`` to never run dry."""
    period = spec.h_max / spec.fps - capacity.round_trip_s
    period = max(period, spec.h_min / spec.fps, MIN_PERIOD_TICKS / spec.fps)
    return capacity.chunk_cost_s / period


_TABLES = itertools.count(1)


class RobotTable(dict):
    """``robot_id -> RobotSpec`` that counts its changes, so a replica's load is summed once per change.

    Each table has its own ``serial`` (never reused, unlike ``id()``), so a view given a new table
    never reads a sum made for an old one.
    """

    version = 0

    def __init__(self, *args: object, **kwargs: RobotSpec) -> None:
        super().__init__(*args, **kwargs)
        self.serial = next(_TABLES)

    def _changed(self) -> None:
        self.version += 1

    def __setitem__(self, key: str, value: RobotSpec) -> None:
        super().__setitem__(key, value)
        self._changed()

    def __delitem__(self, key: str) -> None:
        super().__delitem__(key)
        self._changed()

    def pop(self, *args: object) -> object:  # type: ignore[override]
        value = super().pop(*args)
        self._changed()
        return value

    def popitem(self) -> tuple[str, RobotSpec]:
        item = super().popitem()
        self._changed()
        return item

    def clear(self) -> None:
        super().clear()
        self._changed()

    def update(self, *args: object, **kwargs: RobotSpec) -> None:  # type: ignore[override]
        super().update(*args, **kwargs)
        self._changed()

    def setdefault(self, key: str, default: RobotSpec) -> RobotSpec:  # type: ignore[override]
        value = super().setdefault(key, default)
        self._changed()
        return value


@dataclass
class ReplicaView:
    """What placement knows of one replica.

    Attributes:
        replica_id: its name.
        capacity: its ``d_infer`` and network.
        robots: the robots placed on it, by id (a plain dict assigned here becomes a
            :class:`RobotTable`, whose changes invalidate the summed load).
        healthy: whether it answers its health checks (placement skips it when not).
        max_robots: robots it accepts at most.
        capacity_of: when several policies share the replica's device, each robot's own policy's
            capacity (its ``d_infer`` and cap); None: every robot's is ``capacity``. A robot's
            chunk costs what a batch of *its* policy costs, so a π0.5 robot weighs more than an
            ACT robot of the same timing.
    """

    replica_id: str
    capacity: Capacity
    robots: dict[str, RobotSpec] = field(default_factory=RobotTable)
    healthy: bool = True
    max_robots: int = 64
    capacity_of: Callable[[RobotSpec], Capacity] | None = None

    def __setattr__(self, name: str, value: object) -> None:
        if name == "robots" and not isinstance(value, RobotTable):
            value = RobotTable(value)  # type: ignore[arg-type]
        super().__setattr__(name, value)

    def _sums(self) -> tuple[float, dict[str, float], dict[float, float]]:
        """(total demand, demand per tier, weight-at-or-above memo), recomputed after a change."""
        robots = self.robots
        key = (robots.serial, robots.version, self.capacity, self.capacity_of)  # type: ignore[attr-defined]
        memo = self.__dict__.get("_memo")
        if memo is None or memo[0] != key:
            by_tier: dict[str, float] = {}
            for s in robots.values():
                by_tier[s.tier] = by_tier.get(s.tier, 0.0) + self.demand(s)
            memo = (key, (sum(by_tier.values()), by_tier, {}))
            self.__dict__["_memo"] = memo
        return memo[1]

    def demand(self, spec: RobotSpec) -> float:
        """Device seconds per second ``spec`` needs from this replica (:func:`demand` at its policy's capacity)."""
        return demand(spec, self.capacity if self.capacity_of is None else self.capacity_of(spec))

    def utilization(self, extra: RobotSpec | None = None) -> float:
        """Predicted utilization, with ``extra`` placed too when given."""
        total = self._sums()[0]
        return total + (self.demand(extra) if extra is not None else 0.0)

    def tier_utilization(self, tier: str) -> float:
        """Predicted utilization of this replica's robots of ``tier``."""
        return self._sums()[1].get(tier, 0.0)

    def weight_at_or_above(self, weight: float) -> float:
        """Summed weight of the robots weighing ``weight`` or more."""
        memo = self._sums()[2]
        if weight not in memo:
            memo[weight] = sum(s.weight for s in self.robots.values() if s.weight >= weight)
        return memo[weight]

    @property
    def open(self) -> bool:
        return self.healthy and len(self.robots) < self.max_robots


class NoReplica(Exception):
    """No healthy replica has room for another robot."""


class Placement(abc.ABC):
    """Chooses a replica for a joining robot. Subclasses implement :meth:`_choose`."""

    name = "base"

    def choose(self, spec: RobotSpec, replicas: Sequence[ReplicaView]) -> str:
        """The id of the replica ``spec`` should join (:class:`NoReplica` if none is open)."""
        candidates = [r for r in replicas if r.open]
        if not candidates:
            raise NoReplica("no healthy replica has room for another robot")
        return self._choose(spec, candidates)

    @abc.abstractmethod
    def _choose(self, spec: RobotSpec, candidates: Sequence[ReplicaView]) -> str:
        """The id of one of ``candidates`` (all open) for ``spec``."""


class RandomPlacement(Placement):
    """Any open replica, uniformly (a load balancer that hashes robots to backends)."""

    name = "random"

    def __init__(self, seed: int = 0) -> None:
        self.rng = random.Random(seed)

    def _choose(self, spec: RobotSpec, candidates: Sequence[ReplicaView]) -> str:
        return self.rng.choice(list(candidates)).replica_id


class RoundRobinPlacement(Placement):
    """The next replica in turn, in the order of replica ids."""

    name = "round_robin"

    def __init__(self, seed: int = 0) -> None:
        self.turn = 0

    def _choose(self, spec: RobotSpec, candidates: Sequence[ReplicaView]) -> str:
        ordered = sorted(candidates, key=lambda r: r.replica_id)
        chosen = ordered[self.turn % len(ordered)]
        self.turn += 1
        return chosen.replica_id


class LeastLoadedPlacement(Placement):
    """The replica with the fewest robots ("least connections")."""

    name = "least_loaded"

    def __init__(self, seed: int = 0) -> None:
        pass

    def _choose(self, spec: RobotSpec, candidates: Sequence[ReplicaView]) -> str:
        return min(candidates, key=lambda r: (len(r.robots), r.replica_id)).replica_id


class MirrorAwarePlacement(Placement):
    """The replica with the lowest predicted load once the robot is on it.

    The load is the replica's predicted utilization plus, counted again, the utilization of the
    robot's own tier: robots of one tier have the same deadlines and compete for the same batch
    slots, so they are spread (a greedy choice by total utilization alone puts two fast robots
    together when they happen to join in a row). Each robot's demand is measured against the
    replica's own ``d_infer(b)``, so a slower GPU counts as fuller. Ties go to the replica with
    the least weight already at the robot's weight or above.
    """

    name = "mirror_aware"

    def __init__(self, seed: int = 0) -> None:
        pass

    def _choose(self, spec: RobotSpec, candidates: Sequence[ReplicaView]) -> str:
        def key(r: ReplicaView) -> tuple[float, float, int, str]:
            own = r.demand(spec)
            load = r.utilization() + own + r.tier_utilization(spec.tier) + own
            return (round(load, 9), r.weight_at_or_above(spec.weight), len(r.robots), r.replica_id)

        return min(candidates, key=key).replica_id


def with_unverified(view: ReplicaView, verified: Mapping[str, RobotSpec], unverified: Iterable[str], newcomer: RobotSpec) -> ReplicaView:
    """``view`` as placement should see it when ``newcomer`` joins: the ``verified`` robots (those
    that stream, with the specs their replica granted) as they are, and each ``unverified`` one (a
    registration that has not streamed yet) as one more robot like ``newcomer``.

    A registration's rate and horizons are a claim until the robot streams. Believed, a claim that
    never streams (fps 1000, h_max 1) makes its replica look full, every honest newcomer goes to
    the other replicas, and the front later moves honest robots back to even the load out. Counted
    as the newcomer's equal, it still spreads robots that register together (a failed replica's
    robots all re-register at once), but weighs no more than the robot being placed.
    """
    robots = RobotTable(verified)
    for robot_id in unverified:
        if robot_id not in robots and robot_id != newcomer.robot_id:
            robots[robot_id] = replace(newcomer, robot_id=robot_id)
    return replace(view, robots=robots)


def balanced_choices(spec: RobotSpec, streaming: Sequence[ReplicaView]) -> set[str]:
    """The replicas ``spec`` can join without :func:`rebalance` then wanting to move a robot, judged
    on ``streaming`` (views holding only the robots that stream); every healthy one when the robots
    that stream are unbalanced already, or when no replica keeps them balanced.

    Placement also counts registrations that have not streamed yet (:func:`with_unverified`), so
    that robots registering together spread. Registrations that never stream can still fill one
    replica's side of that count (they are placed too), and honest newcomers then go to the other
    replica until the robots that stream are unbalanced, and the front moves one back. Restricted
    to these replicas, placement never makes the imbalance a move would undo.
    """
    healthy = [v for v in streaming if v.healthy and v.open]
    everyone = {v.replica_id for v in healthy}
    if rebalance(streaming) is not None:
        return everyone
    keep = set()
    for candidate in healthy:
        views = [replace(v, robots={**v.robots, spec.robot_id: spec}) if v is candidate else v for v in streaming]
        if rebalance(views) is None:
            keep.add(candidate.replica_id)
    return keep or everyone


PLACEMENTS: dict[str, Callable[[int], Placement]] = {
    "random": RandomPlacement,
    "round_robin": RoundRobinPlacement,
    "least_loaded": LeastLoadedPlacement,
    "mirror_aware": MirrorAwarePlacement,
}


def make_placement(name: str, seed: int = 0) -> Placement:
    """The placement policy called ``name`` (ConfigError listing the known ones)."""
    if name not in PLACEMENTS:
        raise ConfigError("placement", f"unknown placement {name!r}; known: {', '.join(PLACEMENTS)}")
    return PLACEMENTS[name](seed)


@dataclass(frozen=True)
class Move:
    """Move ``robot_id`` from replica ``source`` to ``target`` (done between two of its chunks)."""

    robot_id: str
    source: str
    target: str


def rebalance(replicas: Sequence[ReplicaView], min_gain: float = 0.05) -> Move | None:
    """One move that lowers the highest predicted utilization by at least ``min_gain``, or None.

    Called when robots join or leave. One move at a time: each costs the moved robot a
    re-registration, so the front makes the best single move and looks again later.
    """
    healthy = [r for r in replicas if r.healthy]
    if len(healthy) < 2:
        return None
    source = max(healthy, key=lambda r: (r.utilization(), r.replica_id))
    before = source.utilization()
    best: tuple[float, Move] | None = None
    for robot_id, spec in sorted(source.robots.items()):
        left = before - source.demand(spec)
        for target in healthy:
            if target is source or not target.open:
                continue
            after = max(left, target.utilization(spec))
            if before - after >= min_gain and (best is None or after < best[0]):
                best = (after, Move(robot_id, source.replica_id, target.replica_id))
    return best[1] if best else None


def place_all(
    specs: Sequence[RobotSpec], replicas: Sequence[ReplicaView], placement: Placement
) -> Mapping[str, str]:
    """Place ``specs`` one after another (their order is the join order); returns robot -> replica."""
    by_id = {r.replica_id: r for r in replicas}
    where: dict[str, str] = {}
    for spec in specs:
        chosen = placement.choose(spec, replicas)
        by_id[chosen].robots[spec.robot_id] = spec
        where[spec.robot_id] = chosen
    return where

"""The cluster's front: robots register here and are answered with the replica to stream to.

This module is the coordinator (:class:`ClusterFront`); its gRPC servicer is in
``front_service.py``. Over 500 lines, kept whole on purpose: the view, placement, moves and rolls
share one lock and one ``state`` table, and splitting them would spread that lock's invariants
over several files.

The front holds no robot state of its own that matters: every few hundred milliseconds it asks
each replica for its ``load`` (the robots streaming there, its ``d_infer`` table) and rebuilds its
view from the answers. Robots stream to replicas directly, so a front that restarts loses no
running robot: they keep streaming, and the new front's first refresh sees them all.

Registration: the front chooses a replica (the robot's current one if it still streams there, a
pending move's target, else the placement policy over the healthy replicas), forwards the
robot's ``RegisterRequest`` to it unchanged (the replica checks features, tokens and the grant
rules as a single server does) and returns the replica's answer with ``stream_address`` set. A
replica that does not answer is marked down and the next choice is tried, so a robot whose
replica died is placed on a live one at its first re-registration. The forwarded registration
names the robot's host, with a proof made with the front's forwarding key
(:mod:`lerobot_armory.serving.forwarding`), which the front hands to every replica instance it
meets: a replica's per-host registration limit then counts each robot host, not the front's.

Rebalancing: when robots joined or left since the last refresh, the front asks
:func:`~lerobot_armory.placement.rebalance` for one move and tells the source replica to release
that robot, which it does between two of the robot's chunks (``Notice.MOVED``); the robot
re-registers here and is steered to the target.

Several policies (``--policies=FILE``): every replica serves every policy of the file. Each robot
is charged at *its* policy's ``d_infer`` and cap on each replica (``ReplicaView.capacity_of``): its
policy is the one its registration names (empty or unknown: the main one, the file's first) while
its placement is pending, and the one its replica reports once it streams.

Swapping the checkpoint (:meth:`ClusterFront.roll`, ``lerobot-armory-admin swap --address=FRONT``):
one policy, one replica at a time, each loading beside its old engine and switching between two
batches (as a single server does); the roll stops at the first replica that refuses or fails, and
the replicas after it keep the old checkpoint. Robots are never moved by a swap. The front
remembers the cluster's policy per name (path and overrides) and brings a replica that restarted
(Ray restarts a dead replica with the options the cluster started with) to every one of them
before placing robots there.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import grpc

from lerobot_armory.entrypoints.cluster.admin import FrontAdminService
from lerobot_armory.entrypoints.cluster.front_service import FrontService
from lerobot_armory.entrypoints.cluster.metrics import FrontMetrics, FrontSnapshot
from lerobot_armory.entrypoints.cluster.replica import ReplicaDown, ReplicaSet, spec_of
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.placement import (
    Capacity,
    Move,
    NoReplica,
    Placement,
    ReplicaView,
    balanced_choices,
    make_placement,
    rebalance,
    with_unverified,
)
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryStub
from lerobot_armory.entrypoints.grpc.service import RunningServer, start_grpc_server
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.serving.security import OperatorTokens
from lerobot_armory.serving.session import DEFAULT_POLICY

log = logging.getLogger(__name__)

# A robot the front just placed is counted on its replica until the replica reports it (or this passes).
PENDING_S = 5.0
# A moved robot is steered to its target for this long, and not moved again for MOVE_COOLDOWN_S.
STEER_S = 10.0
MOVE_COOLDOWN_S = 30.0
# At most one move per this long across the cluster: a burst of joins and leaves (honest or not)
# rebalances one robot at a time, each time against the load the replicas then report.
MOVE_INTERVAL_S = 5.0
MAX_MOVES_KEPT = 1000  # the recent moves, for status and tests
# How long one replica may take to load, warm up and switch to a new checkpoint.
SWAP_TIMEOUT_S = 900.0

Policy = tuple[str, tuple[str, ...]]  # (path, --policy.<field> overrides)


@dataclass
class FrontOptions:
    """The front's knobs (``--cluster.*`` on ``lerobot-armory-cluster``).

    Attributes:
        placement: ``mirror_aware`` (by predicted load), ``least_loaded``, ``round_robin`` or ``random``.
        health_interval_s: how often every replica is asked for its load.
        call_timeout_s: how long a replica may take to answer the front.
        rebalance: move robots between replicas (between chunks) when joins and leaves unbalance them.
        one_way_ms: typical one-way network delay robots see, for the load prediction.
    """

    placement: str = "mirror_aware"
    health_interval_s: float = 0.5
    call_timeout_s: float = 2.0
    rebalance: bool = True
    one_way_ms: float = 3.75

    def validate(self) -> None:
        make_placement(self.placement)
        for name in ("health_interval_s", "call_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"cluster.{name}", f"must be > 0, got {getattr(self, name)}")
        if not self.one_way_ms >= 0:
            raise ConfigError("cluster.one_way_ms", f"must be >= 0, got {self.one_way_ms}")


@dataclass(frozen=True, eq=False)
class RobotPolicies:
    """Robot -> its policy's :class:`Capacity` on one replica (``ReplicaView.capacity_of``).

    Hashable by identity (placement memoizes a replica's load on it): the front makes a new one
    whenever the replica's robots or capacities change. ``policy_of`` is the front's cluster-wide
    map (a robot that placement or a move considers for this replica is charged at its own policy
    here too), never changed in place. A robot not in it, or of a policy the replica does not
    report, is charged at ``default`` (the main policy's).
    """

    capacities: Mapping[str, Capacity]
    policy_of: Mapping[str, str]
    default: Capacity

    def __call__(self, spec: RobotSpec) -> Capacity:
        name = self.policy_of.get(spec.robot_id)
        return self.capacities.get(name, self.default) if name is not None else self.default

    def placing(self, robot_ids: Iterable[str], policy: str) -> RobotPolicies:
        """The same, with ``robot_ids`` (a newcomer, and the registrations counted as its equals) of ``policy``."""
        return RobotPolicies(self.capacities, {**self.policy_of, **dict.fromkeys(robot_ids, policy)}, self.default)


@dataclass
class ReplicaState:
    """The front's view of one replica."""

    view: ReplicaView
    address: str = ""
    chunk_size: int = 0  # the main policy's
    status: str = ""
    pending: dict[str, tuple[RobotSpec, float]] = field(default_factory=dict)  # placed here, not yet reported
    reported: dict[str, RobotSpec] = field(default_factory=dict)
    main: str = DEFAULT_POLICY  # the name of its main (first) policy
    served: dict[str, Policy] = field(default_factory=dict)  # policy name -> what it serves, as last reported
    capacities: dict[str, Capacity] = field(default_factory=dict)  # policy name -> its d_infer and cap
    chunk_sizes: dict[str, int] = field(default_factory=dict)  # policy name -> its chunk size
    reported_policy: dict[str, str] = field(default_factory=dict)  # robot -> its policy, as last reported
    pending_policy: dict[str, str] = field(default_factory=dict)  # robot -> the policy it registered for (pending only)
    swaps: dict[str, int] = field(default_factory=dict)  # its own swaps by result, every policy's
    instance: str = ""  # changes when the replica restarts
    keyed: bool = False  # this instance holds the front's forwarding key: registrations name the robot's host

    @property
    def policy(self) -> Policy | None:
        """What it serves as its main policy, as last reported."""
        return self.served.get(self.main)


@dataclass
class RollResult:
    """The answer to one rolling swap: ``result`` ok, refused or failed (the replica's that stopped
    it); ``message`` one line saying which replicas serve which path."""

    result: str
    message: str
    old_path: str
    new_path: str
    seconds: float = 0.0
    switched: list[str] = field(default_factory=list)  # replicas now on the new path, in order
    policy: str = ""  # the name of the policy rolled


def _served_name(name: str, what: tuple[str, tuple[str, ...]] | None, with_path: bool) -> str:
    """``name``, or ``name=path [overrides]`` where the names agree and the checkpoints do not."""
    if not with_path or what is None:
        return name
    path, overrides = what
    return f"{name}={path}" + (f" [{' '.join(overrides)}]" if overrides else "")


class ClusterFront:
    """The cluster's coordinator: the replicas' view (polled), placement and moves, rolls and the
    forwarding key; its gRPC face (``Register`` places and forwards) is :class:`~lerobot_armory.entrypoints.cluster.front_service.FrontService`."""

    def __init__(
        self,
        replicas: ReplicaSet,
        options: FrontOptions | None = None,
        clock: Callable[[], float] = time.monotonic,
        channel_factory: Callable[[str], grpc.Channel] | None = None,
        forwarding: ForwardingKey | None = None,
    ) -> None:
        self.replicas = replicas
        # Proves to the replicas which robot host a forwarded registration is from (made here, at
        # the front's start: a front started again over running replicas hands them its own).
        self.forwarding = forwarding or ForwardingKey.generate()
        self._keyed: dict[str, tuple[str, bool]] = {}  # replica -> (instance handed the key, whether it took it)
        self.options = options or FrontOptions()
        self.options.validate()
        self.clock = clock
        self.placement: Placement = make_placement(self.options.placement)
        self._channel_factory = channel_factory or (lambda address: grpc.insecure_channel(address))
        self._channels: dict[str, tuple[grpc.Channel, ArmoryStub]] = {}
        self.lock = threading.RLock()
        one_way = self.options.one_way_ms / 1000.0
        # Until a replica first answers, it is unknown: down, with a placeholder capacity.
        self.state: dict[str, ReplicaState] = {
            rid: ReplicaState(ReplicaView(rid, Capacity((1.0,), one_way), healthy=False)) for rid in replicas.ids()
        }
        self.steer: dict[str, tuple[str, float]] = {}  # robot -> (target replica, until)
        self.moved_at: dict[str, float] = {}
        self.moves: list[Move] = []
        self.last_move_at = -1e9
        self._rebalance_due = False  # a membership change whose move waited for MOVE_INTERVAL_S
        self._members: frozenset[tuple[str, str]] = frozenset()  # (robot, replica) pairs and ("", replica up)
        self.admission = AdmissionLimiter()  # registrations per peer host, as on a replica
        self.refused: collections.Counter[str] = collections.Counter()  # registrations refused, by reason
        self.placed: collections.Counter[str] = collections.Counter()  # registrations accepted, by replica
        self.moves_made = 0  # robots released for a move (self.moves keeps only the recent ones)
        # The cluster's policies by name: what every replica should serve, and what a restarted one
        # is brought to. A name is absent until known: the replicas' own when they all agree, or a roll's.
        self.policies: dict[str, Policy] = {}
        self.main = DEFAULT_POLICY  # the main policy's name (robots naming none), as the replicas report it
        self.names: tuple[str, ...] = ()  # the policies the replicas serve, the main one first
        # Robot -> its policy, for the robots the replicas report and those pending (replaced, never
        # changed in place: each replica's view charges its robots through it, RobotPolicies).
        self.policy_of: dict[str, str] = {}
        self.rolls: dict[str, int] = {"ok": 0, "refused": 0, "failed": 0}
        self._roll_lock = threading.Lock()  # one roll (or restarted replica's catch-up) at a time
        self.syncing: set[str] = set()  # replicas being brought to self.policies: no robot is placed there
        self._uneven_warned: frozenset | None = None  # the replicas' differing policies, once warned
        self._behind: set[str] = set()  # replicas a roll skipped (down): brought to the policy when back

    # ---- the view ----------------------------------------------------------------------------

    def snapshot(self) -> FrontSnapshot:
        """The counters and the replicas as the metrics endpoint publishes them (under the lock)."""
        with self.lock:
            replicas = [
                (rid, s.view.healthy, len(s.reported), len(s.pending), s.view.max_robots if s.address else None)
                for rid, s in sorted(self.state.items())
            ]
            return FrontSnapshot(dict(self.refused), dict(self.placed), self.moves_made, replicas)

    def refresh(self) -> None:
        """Ask every replica for its load; rebuild the view; rebalance if membership changed."""
        answers: dict[str, dict[str, Any] | None] = {}
        for rid in self.replicas.ids():
            try:
                answers[rid] = self.replicas.load(rid, self.options.call_timeout_s)
            except ReplicaDown:
                answers[rid] = None
            except Exception as exc:  # noqa: BLE001 - one replica's bad answer must not stop the others' refresh
                log.warning("replica %s answered its load check with %s: %s; counted as down", rid, type(exc).__name__, exc)
                answers[rid] = None
        self._hand_key(answers)
        now = self.clock()
        with self.lock:
            for rid, answer in answers.items():
                state = self.state[rid]
                was = state.view.healthy
                if answer is None or not answer.get("alive", True):
                    state.view.healthy = False
                    state.reported = {}
                    state.reported_policy = {}
                    if was:
                        log.warning("replica %s is down; its robots will be placed elsewhere", rid)
                    continue
                state.address = answer["address"]
                state.chunk_size = int(answer["chunk_size"])
                state.status = answer.get("status", "")
                self._read_policies(state, answer)
                state.view.max_robots = int(answer["max_robots"])
                state.reported = {r["robot_id"]: spec_of(r) for r in answer["robots"]}
                state.reported_policy = {r["robot_id"]: str(r.get("policy") or state.main) for r in answer["robots"]}
                instance = answer.get("instance", "")
                if state.instance and instance != state.instance:
                    log.info("replica %s restarted", rid)
                    self._behind.add(rid)
                state.instance = instance
                state.keyed = self._keyed.get(rid) == (instance, True)
                state.view.healthy = rid not in self.syncing
                if not was and state.view.healthy:
                    log.info("replica %s is up at %s", rid, state.address)
                state.pending = {k: v for k, v in state.pending.items() if k not in state.reported and v[1] > now}
                state.pending_policy = {k: v for k, v in state.pending_policy.items() if k in state.pending}
            self._learn_names(answers)
            self._learn_robot_policies()
            for rid, answer in answers.items():
                if answer is not None and answer.get("alive", True):
                    self._rebuild(self.state[rid])
            # Membership: who streams where, and which replicas are up (a replica back from a
            # restart is empty: robots may move onto it).
            members = frozenset((robot, rid) for rid, s in self.state.items() for robot in s.reported) | frozenset(
                ("", rid) for rid, s in self.state.items() if s.view.healthy
            )
            changed = members != self._members or self._rebalance_due
            self._members = members
            self.steer = {k: v for k, v in self.steer.items() if v[1] > now}
            self.moved_at = {k: t for k, t in self.moved_at.items() if now - t < MOVE_COOLDOWN_S}
            del self.moves[:-MAX_MOVES_KEPT]
            current = {st.address for st in self.state.values()}
            for address in [a for a in self._channels if a not in current]:  # a restarted replica's old port
                self._channels.pop(address)[0].close()
            move = self._plan_move(now) if changed and self.options.rebalance else None
            catch_up = self._plan_catch_up(answers)
        if move is not None:
            self._release(move, now)
        for rid in catch_up:
            threading.Thread(target=self._catch_up, args=(rid,), name=f"armory-front-sync-{rid}", daemon=True).start()

    def _read_policies(self, state: ReplicaState, answer: dict[str, Any]) -> None:
        """Under the lock: the policies a replica's answer reports, each with its capacity and
        checkpoint (a replica of an older version reports its one policy at the top level)."""
        one_way = self.options.one_way_ms / 1000.0
        state.main = str(answer.get("policy_name") or DEFAULT_POLICY)
        policies = answer.get("policies") or {
            state.main: {
                "latency_s": answer["latency_s"], "chunk_size": answer["chunk_size"],
                **({"path": answer["policy_path"], "overrides": answer.get("policy_overrides", ()), "swaps": answer.get("swaps", {})}
                   if "policy_path" in answer else {}),
            }
        }  # fmt: skip
        state.capacities = {name: Capacity(tuple(p["latency_s"]), one_way) for name, p in policies.items()}
        state.chunk_sizes = {name: int(p["chunk_size"]) for name, p in policies.items()}
        state.served = {name: (str(p["path"]), tuple(p.get("overrides", ()))) for name, p in policies.items() if "path" in p}
        state.swaps = {}
        for p in policies.values():
            for result, n in p.get("swaps", {}).items():
                state.swaps[result] = state.swaps.get(result, 0) + int(n)
        state.view.capacity = state.capacities.get(state.main) or Capacity(tuple(answer["latency_s"]), one_way)

    def _learn_names(self, answers: dict[str, dict[str, Any] | None]) -> None:
        """Under the lock: the main policy's name and every policy's, from the replicas that answered."""
        up = [
            self.state[rid] for rid, answer in sorted(answers.items())
            if answer is not None and answer.get("alive", True) and self.state[rid].capacities
        ]  # fmt: skip
        if not up:
            return  # nobody answered: what was known stays
        self.main = up[0].main
        names = [self.main]
        for state in up:
            names += [n for n in state.capacities if n not in names]
        self.names = tuple(names)
        # Every replica should serve every policy, each name the same checkpoint
        # (lerobot-armory-cluster starts them alike). One that does not (started by hand, left from
        # another cluster, or a front restarted beside replicas of another checkpoint) refuses
        # that policy's robots or serves them another model: said once per such state.
        served = {state.view.replica_id: tuple((name, state.served.get(name)) for name in state.capacities) for state in up}
        names_differ = len({tuple(name for name, _ in policies) for policies in served.values()}) > 1
        # Checkpoints differ for a while during every roll and catch-up: only names count then.
        rolling = self._roll_lock.locked()
        uneven = frozenset(served.items()) if names_differ or (len(set(served.values())) > 1 and not rolling) else None
        if uneven is not None and uneven != self._uneven_warned:
            listed = "; ".join(
                f"{rid}: {', '.join(_served_name(n, what, not names_differ) for n, what in policies)}" for rid, policies in sorted(served.items())
            )
            if names_differ:
                log.warning("the replicas serve different policies (%s): a robot of a policy its replica lacks is refused there", listed)
            else:
                log.warning(
                    "the replicas serve different checkpoints under one name (%s): a robot's chunks depend on its replica; "
                    "lerobot-armory-admin swap --policy_name=NAME brings them to one", listed,
                )  # fmt: skip
        if not rolling or uneven is not None:
            self._uneven_warned = uneven

    def policy_names(self) -> tuple[str, ...]:
        """The policies the cluster serves, the main one first (its main one's name until a replica answered)."""
        with self.lock:
            return self.names or (self.main,)

    def policy_for(self, asked: str) -> str:
        """The policy a registration is charged at: the one it names if served, else the main one
        (the replica refuses an unknown name; until then it weighs what a robot of the main policy does)."""
        with self.lock:
            return asked if asked in self.names else self.main

    @property
    def policy(self) -> Policy | None:
        """The cluster's main policy (None: not known yet)."""
        with self.lock:
            return self.policies.get(self.main)

    def _hand_key(self, answers: dict[str, dict[str, Any] | None]) -> None:
        """Give the forwarding key to each replica instance that answered and has not had it (a new
        one, or one restarted). Outside the lock: these are replica calls. One that does not answer
        counts as down; one that cannot take it (a replica of an older version) is told nothing it
        could not check: its per-host limit counts this front's host, as before."""
        for rid, answer in answers.items():
            if answer is None:
                continue
            instance = str(answer.get("instance", ""))
            if rid in self._keyed and self._keyed[rid][0] == instance:
                continue
            try:
                self.replicas.set_forwarding_key(rid, self.forwarding, self.options.call_timeout_s)
            except ReplicaDown:
                answers[rid] = None
                continue
            except Exception as exc:  # noqa: BLE001 - the key is an improvement; the replica still serves
                # The exception's type only: its text could quote the call's arguments.
                log.warning(
                    "replica %s did not take the front's forwarding key (%s): its registration limit counts every "
                    "robot registering through this front as one host", rid, type(exc).__name__,
                )  # fmt: skip
                self._keyed[rid] = (instance, False)
                continue
            self._keyed[rid] = (instance, True)

    # ---- the cluster's policy: rolling swaps, restarted replicas ----------------------------

    def _plan_catch_up(self, answers: dict[str, dict[str, Any] | None]) -> list[str]:
        """Under the lock: learn the cluster's policies; the replicas to bring to them now."""
        if all(answers.values()):
            for name in sorted({n for s in self.state.values() for n in s.served} - set(self.policies)):
                seen = {s.served.get(name) for s in self.state.values()}
                if None not in seen and len(seen) == 1:
                    self.policies[name] = seen.pop()  # every replica answered and serves the same: the cluster's
        if not self.policies:
            self._behind.clear()
            return []
        out = []
        for rid in sorted(self._behind):
            state = self.state[rid]
            if answers.get(rid) is None or rid in self.syncing or not state.served:
                continue
            if all(state.served.get(name) == policy for name, policy in self.policies.items()):
                self._behind.discard(rid)
                continue
            # Out of placement until it serves the cluster's policies (it has no robots: it restarted,
            # or was down during a roll).
            self.syncing.add(rid)
            state.view.healthy = False
            out.append(rid)
        return out

    def _catch_up(self, rid: str) -> None:
        """Bring a replica to every policy the cluster remembers, one swap per policy it serves otherwise."""
        done: list[tuple[str, Policy, dict[str, Any]]] = []
        with self._roll_lock:
            with self.lock:
                wanted = sorted(self.policies.items())
                served = dict(self.state[rid].served)
            for name, policy in wanted:
                if served.get(name) == policy:
                    continue
                try:
                    answer = self.replicas.swap(rid, policy[0], list(policy[1]), False, SWAP_TIMEOUT_S, policy_name=name)
                except Exception as exc:  # noqa: BLE001 - logged; the replica serves what it loaded
                    answer = {"result": "failed", "message": f"{type(exc).__name__}: {exc}"}
                done.append((name, policy, answer))
        with self.lock:
            self.syncing.discard(rid)
            self._behind.discard(rid)
        for name, policy, answer in done:
            if answer["result"] == "ok":
                log.info("replica %s now serves the cluster's policy %s: %s", rid, name, policy[0])
            else:
                log.error(
                    "replica %s could not load the cluster's policy %s: %s (%s: %s): it serves what it started with; "
                    "lerobot-armory-admin status shows each replica's path", rid, name, policy[0],
                    answer["result"], answer.get("message", ""),
                )  # fmt: skip

    def roll(
        self, path: str, overrides: list[str], drain: bool = False, timeout: float = SWAP_TIMEOUT_S, policy_name: str = ""
    ) -> RollResult:
        """Swap policy ``policy_name`` ("": the main one) of every replica to ``path``, one replica
        at a time, stopping at the first that refuses or fails."""
        t0 = time.monotonic()
        name = policy_name or self.policy_names()[0]
        if not self._roll_lock.acquire(blocking=False):
            return self._rolled(RollResult("refused", "another swap is in progress", self.cluster_path(name), path, policy=name), t0)
        try:
            return self._rolled(self._roll(name, path, tuple(overrides), drain, timeout), t0)
        finally:
            self._roll_lock.release()

    def cluster_path(self, name: str = "") -> str:
        """The path of the cluster's policy ``name`` ("": the main one), or the replicas' paths of it while not known."""
        with self.lock:
            name = name or self.main
            if name in self.policies:
                return self.policies[name][0]
            paths = sorted({s.served[name][0] for s in self.state.values() if name in s.served})
            return paths[0] if len(paths) == 1 else ",".join(paths)

    def _roll(self, name: str, path: str, overrides: tuple[str, ...], drain: bool, timeout: float) -> RollResult:
        old = self.cluster_path(name)
        if not path:
            return RollResult("refused", "no policy path given", old, path, policy=name)
        names = self.policy_names()
        if name not in names:
            served = ", ".join(repr(n) for n in names)
            return RollResult("refused", f"no policy named {name[:80]!r}: the cluster serves {served}", old, path, policy=name)
        label = f"{name}=" if len(names) > 1 else ""  # which policy, where the replicas serve several
        with self.lock:
            up = [rid for rid in self.replicas.ids() if self.state[rid].view.healthy]
            down = [rid for rid in self.replicas.ids() if rid not in up]
            was = {rid: self.state[rid].served.get(name, ("?", ()))[0] for rid in self.replicas.ids()}
        if not up:
            return RollResult("refused", "no replica is up; nothing changed", old, path, policy=name)
        switched: list[str] = []
        for rid in up:
            with self.lock:
                if self.state[rid].served.get(name) == (path, overrides):
                    switched.append(rid)  # already serves it (a roll run again after one that stopped)
                    continue
            log.info("rolling swap: %s loads %s%s", rid, label, path)
            try:
                answer = self.replicas.swap(rid, path, list(overrides), drain, timeout, policy_name=name)
            except ReplicaDown as exc:
                answer = {"result": "failed", "message": f"did not answer ({exc})"}
            except Exception as exc:  # noqa: BLE001 - one replica's error stops the roll, told as is
                answer = {"result": "failed", "message": f"{type(exc).__name__}: {exc}"}
            if answer["result"] != "ok":
                rest = [r for r in up if r not in switched]
                where = "; ".join(
                    part for part in (
                        f"{','.join(switched)} serve {label}{path}" if switched else "",
                        f"{','.join(rest)} serve {label}{was[rest[0]]}" if rest else "",
                        f"{','.join(down)} down" if down else "",
                    ) if part
                )  # fmt: skip
                why = str(answer.get("message", "")).replace("\n", " ")
                stopped = f"stopped at {rid} ({answer['result']}: {why}): {where}"
                return RollResult(answer["result"], stopped, old, path, 0.0, switched, name)
            with self.lock:
                self.state[rid].served[name] = (path, overrides)
            switched.append(rid)
        with self.lock:
            self.policies[name] = (path, overrides)
            self._behind |= set(down)  # brought to the new policy when they come back
        tail = f"; {','.join(down)} down, load it when back" if down else ""
        return RollResult("ok", f"{','.join(switched)} serve {label}{path}{tail}", old, path, 0.0, switched, name)

    def _rolled(self, result: RollResult, t0: float) -> RollResult:
        result.seconds = time.monotonic() - t0
        with self.lock:
            self.rolls[result.result] += 1
        if result.result == "ok":
            log.info(
                "rolling swap of %s %s -> %s in %.2f s: %s", result.policy, result.old_path, result.new_path, result.seconds, result.message
            )
        else:
            log.warning("rolling swap of %s %s -> %s %s: %s", result.policy, result.old_path, result.new_path, result.result, result.message)
        return result

    def _rebuild(self, state: ReplicaState) -> None:
        state.view.robots = {**state.reported, **{k: spec for k, (spec, _) in state.pending.items()}}
        state.pending_policy = {k: v for k, v in state.pending_policy.items() if k in state.pending}
        state.view.capacity_of = self._capacity_of(state)

    def _learn_robot_policies(self) -> None:
        """Under the lock: every robot's policy, anew from the robots the replicas report and those
        pending (bounded: no other robot's is kept)."""
        policy_of: dict[str, str] = {}
        for state in self.state.values():
            policy_of.update(state.reported_policy)
            policy_of.update(state.pending_policy)
        self.policy_of = policy_of

    def _capacity_of(self, state: ReplicaState) -> RobotPolicies | None:
        """Each robot's own policy's capacity on this replica (None where it serves one policy). The
        robot -> policy map is the front's, cluster-wide: a robot placement or a move considers for
        this replica is charged at its own policy here too."""
        if len(state.capacities) < 2:
            return None
        return RobotPolicies(dict(state.capacities), self.policy_of, state.view.capacity)

    def _reserve(self, state: ReplicaState, spec: RobotSpec, policy: str) -> None:
        """Count ``spec`` (of ``policy``) on the replica until it reports the robot (or PENDING_S passes)."""
        state.pending[spec.robot_id] = (spec, self.clock() + PENDING_S)
        state.pending_policy[spec.robot_id] = policy
        if self.policy_of.get(spec.robot_id) != policy:
            # A new map, never one changed in place: a view keeps the one its load was summed with.
            self.policy_of = {**self.policy_of, spec.robot_id: policy}
        self._rebuild(state)

    @staticmethod
    def _placing(view: ReplicaView, robots: Iterable[str], policy: str) -> ReplicaView:
        """``view`` as placement weighs it for a newcomer of ``policy``: ``robots`` (the newcomer, and
        the registrations counted as its equals) charged at that policy's capacity."""
        if not isinstance(view.capacity_of, RobotPolicies):
            return view
        return replace(view, capacity_of=view.capacity_of.placing(robots, policy))

    def _plan_move(self, now: float) -> Move | None:
        """The next move, planned on the robots that stream (as the replicas report them): a
        registration that never streams counts for placement while pending (as one more robot like
        the one being placed), never for a move."""
        self._rebalance_due = now - self.last_move_at < MOVE_INTERVAL_S
        if self._rebalance_due:
            return None
        views = [replace(s.view, robots=dict(s.reported)) for s in self.state.values()]
        move = rebalance(views)
        if move is None or now - self.moved_at.get(move.robot_id, -1e9) < MOVE_COOLDOWN_S:
            return None
        return move

    def _release(self, move: Move, now: float) -> None:
        with self.lock:
            self.steer[move.robot_id] = (move.target, now + STEER_S)
            self.moved_at[move.robot_id] = now
            self.last_move_at = now
        try:
            released = self.replicas.release(move.source, move.robot_id, self.options.call_timeout_s)
        except ReplicaDown:
            released = False
        if released:
            with self.lock:
                self.moves.append(move)
                self.moves_made += 1
            log.info("rebalancing: moving %s from %s to %s (between two of its chunks)", move.robot_id, move.source, move.target)

    def placements(self) -> dict[str, str]:
        """Robot -> replica, as last reported by the replicas (pending placements included)."""
        with self.lock:
            return {robot: rid for rid, s in sorted(self.state.items()) for robot in s.view.robots if s.view.healthy}

    def describe(self) -> str:
        """One line per replica: health, address, robots, predicted utilization."""
        with self.lock:
            lines = []
            for rid, s in sorted(self.state.items()):
                health = "up" if s.view.healthy else "DOWN"
                util = s.view.utilization() if s.view.healthy else 0.0
                robots = ",".join(sorted(s.view.robots)) or "-"
                lines.append(f"  {rid} {health:<4} {s.address or '-':<21} util={util:.2f} robots={robots}")
            return "\n".join(lines)

    # ---- registration: placement (the gRPC servicer forwards, front_service.py) -----------------

    def choices(self, request: pb.RegisterRequest) -> Iterator[str]:
        """Replicas to try for a robot, best first, each at most once."""
        tried: set[str] = set()
        robot = request.robot_id
        with self.lock:
            steered = self.steer.get(robot, ("", 0.0))[0]
            current = next((rid for rid, s in self.state.items() if robot in s.reported and s.view.healthy), "")
        for rid in (steered, current):
            if rid and rid not in tried:
                tried.add(rid)
                yield rid
        while True:
            with self.lock:
                views = [s.view for rid, s in self.state.items() if rid not in tried]
                spec = self._spec(request)
                policy = self.policy_for(request.policy_name)
                # The robots that stream stay balanced whatever is chosen (placement.balanced_choices):
                # registrations that never stream cannot push newcomers onto one replica.
                streaming = [
                    self._placing(replace(s.view, robots=dict(s.reported)), (robot,), policy)
                    for rid, s in self.state.items() if rid not in tried
                ]  # fmt: skip
                keep = balanced_choices(spec, streaming) if spec is not None else set()
                try:
                    if spec is not None:
                        # A registration that has not streamed yet counts as one more robot like
                        # this one, whatever it claimed (placement.with_unverified), of its policy.
                        placed = [
                            self._placing(with_unverified(s.view, s.reported, s.pending, spec), [robot, *(k for k in s.pending if k not in s.reported)], policy)
                            for rid, s in self.state.items() if rid not in tried
                        ]  # fmt: skip
                        rid = self.placement.choose(spec, [v for v in placed if v.replica_id in keep and v.open] or placed)
                    else:  # the replica will refuse it and say why: any open one answers
                        rid = min((v for v in views if v.open), key=lambda v: (len(v.robots), v.replica_id)).replica_id
                except (NoReplica, ValueError):
                    # Every replica looks full to placement. A replica makes room itself (it drops
                    # registrations that never streamed and robots that stopped asking), so the
                    # healthy ones decide, least loaded first; they refuse if they cannot.
                    healthy = sorted((v for v in views if v.healthy), key=lambda v: (len(v.robots), v.replica_id))
                    healthy = [v for v in healthy if v.replica_id in keep] or healthy
                    if not healthy:
                        return
                    rid = healthy[0].replica_id
                state = self.state[rid]
                if spec is not None and state.view.healthy and state.address:
                    # Reserved with the choice, under the same lock: robots registering at the same
                    # moment see each other and spread (Register reserves it again before its call).
                    self._reserve(state, spec, policy)
            tried.add(rid)
            yield rid

    def _spec(self, request: pb.RegisterRequest) -> RobotSpec | None:
        """The robot as placement sees it: its claims, with its policy's chunk size."""
        policy = self.policy_for(request.policy_name)
        chunk = max((s.chunk_sizes.get(policy, s.chunk_size) for s in self.state.values() if s.view.healthy), default=0)
        try:
            # Placement weighs at most 1 here: the replica's grant rules grant the real weight,
            # and a robot must not buy a lighter replica by asking for a heavy one.
            return RobotSpec(request.robot_id, request.fps, chunk, request.h_min, request.h_max, min(request.weight, 1.0), request.tier)
        except (ConfigError, TypeError, ValueError):
            return None

    def stub(self, address: str) -> ArmoryStub:
        """The gRPC stub of a replica's address (one channel each, closed when the replica moves)."""
        with self.lock:
            if address not in self._channels:
                channel = self._channel_factory(address)
                self._channels[address] = (channel, ArmoryStub(channel))
            return self._channels[address][1]

    def reserve_for(self, rid: str, request: pb.RegisterRequest) -> tuple[str, bool]:
        """Reserve room on replica ``rid`` for a registration about to be forwarded there: (its
        address, "" when it is down; whether it took this front's forwarding key). Reserved before
        the call: robots registering at the same moment (the robots of a replica that just died)
        see each other and spread."""
        with self.lock:
            state = self.state[rid]
            address = state.address if state.view.healthy else ""
            spec = self._spec(request)
            if address and spec is not None:
                self._reserve(state, spec, self.policy_for(request.policy_name))
            return address, state.keyed

    def placed_on(self, rid: str, robot_id: str) -> None:
        """``rid`` took the robot: counted, and it is pending nowhere else."""
        with self.lock:
            self.placed[rid] += 1
            for other_id, other in self.state.items():
                if other_id != rid:
                    other.pending.pop(robot_id, None)
                    other.reported.pop(robot_id, None)
                    self._rebuild(other)

    def refused_for(self, why: str) -> None:
        """A registration refused, counted by reason (``armory_front_registrations_refused_total``)."""
        with self.lock:
            self.refused[why] += 1

    def unreserve(self, rid: str, robot_id: str) -> None:
        with self.lock:
            state = self.state[rid]
            if state.pending.pop(robot_id, None) is not None:
                self._rebuild(state)

    def mark_down(self, rid: str) -> None:
        with self.lock:
            state = self.state[rid]
            if state.view.healthy:
                log.warning("replica %s did not answer a registration; marked down until it answers again", rid)
            state.view.healthy = False
            state.reported = {}
            state.reported_policy = {}


class FrontServer:
    """The front on a gRPC port, with its health loop."""

    def __init__(
        self,
        front: ClusterFront,
        host: str = "127.0.0.1",
        port: int = 0,
        max_message_bytes: int = 4 << 20,
        tls: tuple[bytes, bytes] | None = None,
        operators: OperatorTokens | None = None,
    ) -> None:
        self.front = front
        self.metrics = FrontMetrics(front.snapshot)
        self._stop_metrics: Callable[[], None] | None = None
        # The operator's calls (lerobot-armory-admin swap|status), refused without operator tokens.
        self.admin = FrontAdminService(front, operators)
        self.service = FrontService(front)
        self.grpc: RunningServer = start_grpc_server(self.service, host, port, 256, max_message_bytes, tls, admin=self.admin)  # type: ignore[arg-type]
        self.host = host
        self._stop = threading.Event()
        front.refresh()
        self._thread = threading.Thread(target=self._loop, name="armory-front-health", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.grpc.port

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def serve_metrics(self, port: int) -> int:
        """Start the front's Prometheus endpoint on its gRPC host; returns the port bound (0: a free one)."""
        bound, self._stop_metrics = self.metrics.serve(port, self.host)
        return bound

    def _loop(self) -> None:
        while not self._stop.wait(self.front.options.health_interval_s):
            try:
                self.front.refresh()
            except Exception:
                log.exception("refreshing the replicas' load failed")

    def stop(self, grace_s: float = 1.0) -> None:
        self._stop.set()
        self.grpc.set_serving(False)
        self.grpc.server.stop(grace_s).wait()
        self._thread.join(timeout=5)
        if self._stop_metrics is not None:
            self._stop_metrics()
            self._stop_metrics = None

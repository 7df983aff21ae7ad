"""One replica of a cluster, and the sets of replicas a front talks to.

A replica *is* ``lerobot-armory-server``: :func:`~lerobot_armory.entrypoints.server.build_server` with the
user's options on a free port. It adds calls for the front: ``info`` (where it listens, and per
policy served its ``d_infer`` table, chunk size and checkpoint), ``load`` (info plus the robots it
serves and each one's policy, from its own fleet: the front rebuilds its whole view from these, so
a restarted front loses nothing), ``release`` (move a robot away between two of its chunks),
``swap`` (load another checkpoint of one policy beside the served one and switch between batches,
as ``lerobot-armory-admin swap`` does on a single server: the front rolls a swap replica by
replica) and ``set_forwarding_key`` (the key with
which the front proves which robot host a forwarded registration is from: serving/forwarding.py).

:class:`ArmoryReplica` is a plain class; Ray runs it as an actor (:class:`RayReplicas`), tests
and single-host setups can hold it in-process (:class:`LocalReplicas`). The front sees either
through :class:`ReplicaSet`, whose calls raise :class:`ReplicaDown` for a replica that does not
answer in time, whatever the transport.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import uuid
from collections.abc import Callable
from typing import Any, Protocol

from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.entrypoints.server import ArmoryServer, build_server
from lerobot_armory.serving.config import ServerConfig
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.serving.swap import SwapResult

log = logging.getLogger(__name__)

WILDCARD_HOSTS = ("0.0.0.0", "::", "")


class ReplicaDown(Exception):
    """A replica did not answer (dead, restarting, or unreachable)."""


def advertised_host(bind_host: str, node_ip: Callable[[], str] | None = None) -> str:
    """The host robots reach a replica at: the bind host, or this node's IP when bound to all."""
    if bind_host not in WILDCARD_HOSTS:
        return bind_host
    if node_ip is not None:
        return node_ip()
    return socket.gethostbyname(socket.gethostname())


class ArmoryReplica:
    """One replica: the whole server, on its own port.

    Args:
        cfg: the server's options (as ``lerobot-armory-server`` takes them); its ``port`` is
            ignored (each replica binds a free one) unless ``port`` is given.
        replica_id: the replica's name in the cluster.
        advertise_host: the host robots are told to stream to ("" : from ``cfg.host``).
        port: a fixed port (0: a free one).
    """

    def __init__(self, cfg: ServerConfig, replica_id: str, advertise_host: str = "", port: int = 0) -> None:
        self.replica_id = replica_id
        cfg = dataclasses.replace(cfg, port=port, metrics_port=None, batch_log=None)
        self.server: ArmoryServer
        self.server, self.summary = build_server(cfg)
        host = advertise_host or advertised_host(cfg.host, _ray_node_ip)
        self.address = f"{host}:{self.server.port}"
        self.instance = uuid.uuid4().hex  # a replica restarted (by Ray) is a new instance
        log.info("replica %s serving at %s (pid %d)", replica_id, self.address, os.getpid())

    def info(self) -> dict[str, Any]:
        """Where it listens and what it can serve: id, address, limits and, in ``policies``, each
        policy served by name (its ``d_infer`` table in s, chunk size, checkpoint, swaps). The
        top-level ``latency_s``, ``chunk_size``, ``policy*`` and ``swaps`` are the first (main)
        policy's, ``policy_name`` its name, as replicas serving one policy answered."""
        policies = {name: self._policy(name) for name in self.server.swappers}
        main = self.server.loop.default_policy
        first = policies[main]
        return {
            "replica_id": self.replica_id,
            "address": self.address,
            "latency_s": first["latency_s"],
            "max_robots": self.server.fleet.max_robots,
            "chunk_size": first["chunk_size"],
            "policy": first["description"],
            "policy_path": first["path"],
            "policy_overrides": first["overrides"],
            "swaps": first["swaps"],
            "policy_name": main,
            "policies": policies,
            "pid": os.getpid(),
            "instance": self.instance,
        }

    def _policy(self, name: str) -> dict[str, Any]:
        """One served policy: its scheduler's ``d_infer`` for b = 1..its cap, chunk size, checkpoint, swaps."""
        swapper = self.server.swappers[name]
        scheduler = self.server.loop.policies[name].scheduler
        current = swapper.current
        return {
            "latency_s": list(scheduler.d_infer[: getattr(scheduler, "max_batch_size", None)]),
            "chunk_size": current.shape.chunk_size,
            "description": current.description,
            "path": current.path,
            "overrides": list(current.options.overrides),
            "swaps": dict(swapper.counts.by_result),
        }

    def load(self) -> dict[str, Any]:
        """``info`` plus the robots streaming here (their granted specs and policies) and a status line."""
        with self.server.fleet.cond:
            robots = [
                {**dataclasses.asdict(s.spec), "starvation_pct": s.counters.reported_starvation_pct, "policy": s.policy}
                for s in self.server.fleet.active()
            ]
        return {**self.info(), "robots": robots, "status": self.server.status_line(), "alive": self.server.loop.alive}

    def release(self, robot_id: str) -> bool:
        """Move ``robot_id`` away between two of its chunks (False: it does not stream here)."""
        return self.server.fleet.release(robot_id)

    def swap(self, path: str, overrides: list[str], drain: bool = False, policy_name: str = "") -> dict[str, Any]:
        """Serve ``path`` as policy ``policy_name`` ("": the main one) from the next batch
        (serving/swap.py); its :class:`SwapResult` as a dict (refused: no policy of that name)."""
        name = policy_name or self.server.loop.default_policy
        swapper = self.server.swappers.get(name)
        if swapper is None:
            names = ", ".join(repr(n) for n in self.server.swappers)
            return dataclasses.asdict(SwapResult("refused", f"no policy named {name[:80]!r}: {self.replica_id} serves {names}", "", path))
        return dataclasses.asdict(swapper.swap(path, overrides, drain))

    def set_forwarding_key(self, key: ForwardingKey) -> None:
        """Count registrations the front forwards against the robot host it proves with ``key``
        (it replaces any earlier front's). Given by the front, over the control plane, to every
        replica instance it meets: one Ray restarted and one a front started again found keep the
        per-host limit per robot host."""
        self.server.service.forwarding = key

    def stop(self) -> None:
        """Stop serving (robots are told, as on a server's shutdown)."""
        self.server.stop()


def _ray_node_ip() -> str:
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # noqa: BLE001 - outside Ray: this host's name resolves as well as it can
        return socket.gethostbyname(socket.gethostname())


def spec_of(robot: dict[str, Any]) -> RobotSpec:
    """A robot's spec from a replica's ``load`` entry."""
    fields = {f.name for f in dataclasses.fields(RobotSpec)}
    return RobotSpec(**{k: v for k, v in robot.items() if k in fields})


class ReplicaSet(Protocol):
    """The replicas a front places robots on, whatever runs them."""

    def ids(self) -> list[str]:
        """Replica ids, stable for the cluster's life (a restarted replica keeps its id)."""
        ...

    def load(self, replica_id: str, timeout: float) -> dict[str, Any]:
        """The replica's :meth:`ArmoryReplica.load` (:class:`ReplicaDown` if it does not answer)."""
        ...

    def release(self, replica_id: str, robot_id: str, timeout: float) -> bool:
        """The replica's :meth:`ArmoryReplica.release` (:class:`ReplicaDown` if it does not answer)."""
        ...

    def swap(
        self, replica_id: str, path: str, overrides: list[str], drain: bool, timeout: float, policy_name: str = ""
    ) -> dict[str, Any]:
        """The replica's :meth:`ArmoryReplica.swap` (:class:`ReplicaDown` if it does not answer)."""
        ...

    def set_forwarding_key(self, replica_id: str, key: ForwardingKey, timeout: float) -> None:
        """The replica's :meth:`ArmoryReplica.set_forwarding_key` (:class:`ReplicaDown` if it does not answer)."""
        ...


class LocalReplicas:
    """Replicas held in this process (tests, and one host without Ray). ``kill`` stops one."""

    def __init__(self, replicas: dict[str, ArmoryReplica]) -> None:
        self.replicas: dict[str, ArmoryReplica | None] = dict(replicas)

    def ids(self) -> list[str]:
        return sorted(self.replicas)

    def _get(self, replica_id: str) -> ArmoryReplica:
        replica = self.replicas.get(replica_id)
        if replica is None:
            raise ReplicaDown(f"replica {replica_id} is down")
        return replica

    def load(self, replica_id: str, timeout: float) -> dict[str, Any]:
        return self._get(replica_id).load()

    def release(self, replica_id: str, robot_id: str, timeout: float) -> bool:
        return self._get(replica_id).release(robot_id)

    def swap(
        self, replica_id: str, path: str, overrides: list[str], drain: bool, timeout: float, policy_name: str = ""
    ) -> dict[str, Any]:
        return self._get(replica_id).swap(path, overrides, drain, policy_name)

    def set_forwarding_key(self, replica_id: str, key: ForwardingKey, timeout: float) -> None:
        self._get(replica_id).set_forwarding_key(key)

    def kill(self, replica_id: str) -> None:
        """Stop a replica abruptly (its robots' streams end)."""
        replica = self.replicas.get(replica_id)
        self.replicas[replica_id] = None
        if replica is not None:
            replica.server.stop(grace_s=0.0)


class RayReplicas:
    """Replicas run as Ray actors (named, so a restarted front finds them again)."""

    def __init__(self, handles: dict[str, Any]) -> None:
        self.handles = dict(handles)

    def ids(self) -> list[str]:
        return sorted(self.handles)

    def _call(self, replica_id: str, method: str, *args: Any, timeout: float) -> Any:
        import ray
        from ray import exceptions as rex

        try:
            return ray.get(getattr(self.handles[replica_id], method).remote(*args), timeout=timeout)
        except (rex.GetTimeoutError, rex.RayActorError, rex.ActorUnavailableError) as exc:
            raise ReplicaDown(f"replica {replica_id}: {type(exc).__name__}") from None

    def load(self, replica_id: str, timeout: float) -> dict[str, Any]:
        return self._call(replica_id, "load", timeout=timeout)

    def release(self, replica_id: str, robot_id: str, timeout: float) -> bool:
        return self._call(replica_id, "release", robot_id, timeout=timeout)

    def swap(
        self, replica_id: str, path: str, overrides: list[str], drain: bool, timeout: float, policy_name: str = ""
    ) -> dict[str, Any]:
        return self._call(replica_id, "swap", path, overrides, drain, policy_name, timeout=timeout)

    def set_forwarding_key(self, replica_id: str, key: ForwardingKey, timeout: float) -> None:
        self._call(replica_id, "set_forwarding_key", key, timeout=timeout)

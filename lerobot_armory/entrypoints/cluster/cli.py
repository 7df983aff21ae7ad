"""``lerobot-armory-cluster``: K replicas of the server as Ray actors, and the front robots register with.

    lerobot-armory-cluster --policy.path=lerobot/pi05_base --replicas=4 --port=8080
    lerobot-armory-cluster --policy.path=... --replicas=8 --ray.address=auto --replica.host=0.0.0.0
    lerobot-armory-cluster --policies=policies.yaml --replicas=4   # every replica serves every policy

Every ``lerobot-armory-server`` option applies to each replica (``--policy.*``, ``--scheduler.*``,
``--max_batch_size``, ``--fleet.rules``, ``--auth_token_file`` ...); ``--port`` is the front's, and so
is ``--metrics_port`` (the front's registrations placed and refused by reason, its moves, its view of
the replicas; the replicas publish no metrics port of their own).
Robots use ``--server_address=`` the front and nothing else changes.

``--policies=FILE`` (as on the server): every replica serves every policy of the file (the file
and the checkpoints must be readable at the same paths on every node). Robots name theirs with
``--policy_name``; the front charges each robot its own policy's load on each replica, and
``lerobot-armory-admin swap --policy_name=NAME`` rolls that policy replica by replica.

Ray places the replicas (one GPU each by default), restarts one that dies, and keeps them when
this process exits if they run in a cluster started with ``ray start --head``
(``--ray.address=auto``): the replicas are *detached, named* actors, and a front started again
finds them by name, with every robot still streaming.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import grpc

from lerobot_armory.cli_util import run_or_exit
from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, RayReplicas
from lerobot_armory.errors import ConfigError
from lerobot_armory.serving.config import ServerConfig, parse_server_args
from lerobot_armory.serving.logs import configure_logging
from lerobot_armory.serving.policies_file import load_policies
from lerobot_armory.serving.security import AuthTokens, OperatorTokens, read_tls

log = logging.getLogger("lerobot_armory.cluster")

NAME_PREFIX = "armory-replica-"
START_TIMEOUT_S = 600.0  # loading and warming a VLA on a cold node takes minutes


@dataclass
class RayOptions:
    """``--ray.address``: an existing Ray cluster (``auto``: the one ``ray start`` made on this
    host); unset: a local cluster in this process (it ends with it). ``--ray.namespace``: where
    the named replicas live (two clusters on one Ray cluster need two namespaces)."""

    address: str | None = None
    namespace: str = "lerobot-armory"


@dataclass
class ReplicaOptions:
    """Per replica: ``--replica.num_gpus`` (0: a CPU replica), ``--replica.num_cpus``,
    ``--replica.host`` (bind address; ``0.0.0.0`` to reach replicas on other hosts, which then
    advertise their node's IP; default: ``--host``), ``--replica.max_restarts`` (-1: always)."""

    num_gpus: float = 1.0
    num_cpus: float = 1.0
    host: str | None = None
    max_restarts: int = -1


@dataclass
class ClusterConfig(ServerConfig):
    """Options of ``lerobot-armory-cluster``: the server's, plus the cluster's own. ``--port`` and
    ``--metrics_port`` are the front's."""

    replicas: int = 2
    ray: RayOptions = field(default_factory=RayOptions)
    replica: ReplicaOptions = field(default_factory=ReplicaOptions)
    cluster: FrontOptions = field(default_factory=FrontOptions)

    def validate(self) -> None:
        super().validate()
        if self.replicas < 1:
            raise ConfigError("replicas", f"must be >= 1, got {self.replicas}")
        if self.replica.num_gpus < 0 or self.replica.num_cpus < 0:
            raise ConfigError("replica", "num_gpus and num_cpus must be >= 0")
        self.cluster.validate()

    def replica_config(self) -> ServerConfig:
        """What each replica serves with: the server's options, its own bind host, a free port."""
        base = {f.name: getattr(self, f.name) for f in dataclasses.fields(ServerConfig)}
        base["host"] = self.replica.host or self.host
        base["port"] = 0
        base["metrics_port"] = None  # --metrics_port is the front's
        base["status_interval_s"] = 0.0
        if self.policies:  # read by each replica, whose working directory may not be this one
            base["policies"] = os.path.abspath(self.policies)
        return ServerConfig(**base)

    def served(self) -> str:
        """What each replica serves, for the start-up lines: the path, or ``name=path, ...``."""
        if not self.policies:
            return str(self.policy.path)
        return ", ".join(f"{e.name}={e.path}" for e in load_policies(self.policies))


def preflight(cfg: ClusterConfig) -> None:
    """Every check that needs no Ray and no model: a bad option, grant rules file or policies
    file is one line here, not K tracebacks in the replicas."""
    cfg.validate()
    cfg.fleet.load()
    if cfg.policies:
        load_policies(cfg.policies)


def start_replicas(cfg: ClusterConfig) -> RayReplicas:
    """Find or start the K named replica actors; wait until each serves. Ray must be initialised."""
    import ray

    gpus = ray.cluster_resources().get("GPU", 0.0)
    need = cfg.replicas * cfg.replica.num_gpus
    if need > gpus:
        raise ConfigError(
            "replica.num_gpus",
            f"{cfg.replicas} replicas x {cfg.replica.num_gpus:g} GPU need {need:g} GPUs and the Ray cluster has {gpus:g}; "
            "add nodes (ray start --address=...), lower --replicas, or use --replica.num_gpus=0 for CPU replicas",
        )
    names = [e.name for e in load_policies(cfg.policies)] if cfg.policies else []
    actor = ray.remote(ArmoryReplica)
    handles: dict[str, Any] = {}
    detached = cfg.ray.address is not None
    for k in range(cfg.replicas):
        rid = f"{NAME_PREFIX}{k}"
        handles[rid] = actor.options(
            name=rid,
            namespace=cfg.ray.namespace,
            get_if_exists=True,  # a front started again attaches to the replicas already serving
            lifetime="detached" if detached else None,
            max_restarts=cfg.replica.max_restarts,
            max_concurrency=4,  # load checks and releases go on while a swap loads a checkpoint
            num_gpus=cfg.replica.num_gpus,
            num_cpus=cfg.replica.num_cpus,
        ).remote(cfg.replica_config(), rid)
    started = time.monotonic()
    pending = {rid: h.info.remote() for rid, h in handles.items()}
    while pending:
        done, _ = ray.wait(list(pending.values()), num_returns=1, timeout=5.0)
        for ref in done:
            rid = next(r for r, v in pending.items() if v == ref)
            info = ray.get(ref)  # a replica that failed to start raises here with its own error
            if cfg.policies and set(info.get("policies", ())) != set(names):
                # get_if_exists found a replica of an earlier cluster serving other policies.
                raise ConfigError(
                    "replicas",
                    f"{rid} already runs in Ray namespace {cfg.ray.namespace!r} serving the policies "
                    f"{', '.join(info.get('policies', ())) or info['policy']}, not {', '.join(names)}: stop the old cluster's "
                    "replicas first, or use another --ray.namespace",
                )
            if cfg.policy.path and cfg.policy.path not in info["policy"]:
                # get_if_exists found a replica of an earlier cluster: it keeps its own options.
                raise ConfigError(
                    "replicas",
                    f"{rid} already runs in Ray namespace {cfg.ray.namespace!r} serving {info['policy']}, not "
                    f"{cfg.policy.path}: stop the old cluster's replicas first, or use another --ray.namespace",
                )
            what = ", ".join(f"{n}: {p['description']}" for n, p in info["policies"].items()) if cfg.policies else info["policy"]
            print(f"  replica {rid} serving at {info['address']} (pid {info['pid']}, {what})", flush=True)
            del pending[rid]
        if pending and time.monotonic() - started > START_TIMEOUT_S:
            raise ConfigError("replicas", f"{len(pending)} replicas did not start in {START_TIMEOUT_S:.0f} s: {', '.join(pending)}")
        if pending and not done:
            what = "policies" if cfg.policies else "policy"
            print(f"  waiting for {len(pending)} replicas to load the {what} ({time.monotonic() - started:.0f} s)...", flush=True)
    extra = sorted(
        name for name in ray.util.list_named_actors() if name.startswith(NAME_PREFIX) and name not in handles
    )
    if extra:
        log.warning(
            "Ray namespace %r also holds %s from an earlier, larger cluster: the front does not place robots on them "
            "or fail their robots over; ray.kill them if they are not wanted",
            cfg.ray.namespace, ", ".join(extra),
        )  # fmt: skip
    return RayReplicas(handles)


def run(cfg: ClusterConfig) -> None:
    """Start (or attach to) the replicas, serve the front until a signal."""
    preflight(cfg)
    configure_logging(cfg.log_level, cfg.log_format)
    try:
        import ray
    except ImportError:
        raise ConfigError("replicas", "the cluster needs Ray: pip install 'lerobot-armory[cluster]'") from None
    ray.init(address=cfg.ray.address, namespace=cfg.ray.namespace, include_dashboard=False, log_to_driver=True)
    print(f"lerobot-armory-cluster: starting {cfg.replicas} replicas of {cfg.served()} on Ray ...", flush=True)
    replicas = start_replicas(cfg)
    tls = read_tls(cfg.tls_cert, cfg.tls_key)
    auth = AuthTokens.load(cfg.auth_token_file) if cfg.auth_token_file else None
    operators = OperatorTokens.load(cfg.operator_token_file, auth) if cfg.operator_token_file else None
    channels = None
    if tls is not None:
        # The replicas serve TLS with the same certificate (it must name every replica's host):
        # the front trusts it to forward registrations.
        cert = tls[1]
        channels = lambda address: grpc.secure_channel(address, grpc.ssl_channel_credentials(root_certificates=cert))
    front = FrontServer(
        ClusterFront(replicas, cfg.cluster, channel_factory=channels), cfg.host, cfg.port, int(cfg.max_message_mb * (1 << 20)), tls,
        operators,
    )
    metrics_port = front.serve_metrics(cfg.metrics_port) if cfg.metrics_port is not None else None
    print(
        f"lerobot-armory-cluster front listening on {front.address}: robots use --server_address={front.address}\n"
        f"  metrics: {f'http://{cfg.host}:{metrics_port}/metrics' if metrics_port is not None else 'off'}\n"
        f"  placement: {cfg.cluster.placement}, health checks every {cfg.cluster.health_interval_s:g} s, "
        f"rebalancing {'on' if cfg.cluster.rebalance else 'off'}, "
        f"{'operator token (lerobot-armory-admin rolls swaps replica by replica)' if operators else 'admin calls off'}\n"
        f"{front.front.describe()}",
        flush=True,
    )
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    while not stop.wait(max(1.0, cfg.status_interval_s or 1.0)):
        if cfg.status_interval_s > 0:
            log.info("cluster:\n%s", front.front.describe())
    front.stop()
    if cfg.ray.address is not None:
        print("front stopped; the replicas keep serving their robots (detached): start the front again to place new ones")
    else:
        print("front stopped; the local Ray cluster and its replicas stop with this process")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``--policy.<field>=value`` passes through as on the server)."""
    run_or_exit(run, parse_server_args(ClusterConfig, argv, "lerobot-armory-cluster"), "lerobot-armory-cluster")


if __name__ == "__main__":
    main()

"""Prometheus metrics of the cluster front (``--metrics_port`` of ``lerobot-armory-cluster``).

The front's counters (registrations placed and refused, moves) and its view of the replicas are
read from :class:`~lerobot_armory.entrypoints.cluster.front.ClusterFront` when Prometheus
scrapes (a custom collector, as the server's own metrics), so registrations pay nothing for them.
The replicas' own metrics stay on the replicas; the front publishes what only it knows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

# Every reason the front refuses a registration for (ClusterFront._refuse), published at 0 from
# the start so that a dashboard's rate() sees the first refusal.
REFUSAL_REASONS = ("rate", "replica_rate", "full", "unavailable", "down")


@dataclass
class FrontSnapshot:
    """What the front's metrics read, taken under the front's lock (``ClusterFront.snapshot``).

    Attributes:
        refused: registrations refused, by reason.
        placed: registrations placed, by replica.
        moves: robots moved between replicas.
        replicas: ``(replica, healthy, streaming robots, pending registrations, max robots or None)``.
    """

    refused: dict[str, int] = field(default_factory=dict)
    placed: dict[str, int] = field(default_factory=dict)
    moves: int = 0
    replicas: list[tuple[str, bool, int, int, int | None]] = field(default_factory=list)


class FrontCollector(Collector):
    """The front's counters and its view of each replica, from a snapshot per scrape."""

    def __init__(self, snapshot: Callable[[], FrontSnapshot]) -> None:
        self.snapshot = snapshot

    def collect(self) -> Iterator:
        snap = self.snapshot()
        refused, placed, moves, replicas = snap.refused, snap.placed, snap.moves, snap.replicas
        refused_f = CounterMetricFamily(
            "armory_front_registrations_refused",
            "Registrations the front refused, by reason: rate (the front's per-host limit), replica_rate (the replicas' "
            "own limit: per robot host, as the front proves it, or per credential), full (every replica full of robots "
            "that ask), unavailable (replicas answered but none could take it), down (no replica up)",
            labels=["reason"],
        )
        for reason in sorted(set(REFUSAL_REASONS) | set(refused)):
            refused_f.add_metric([reason], refused.get(reason, 0))
        placed_f = CounterMetricFamily(
            "armory_front_registrations_placed", "Registrations a replica accepted through the front", labels=["replica"]
        )
        up = GaugeMetricFamily("armory_front_replica_up", "1 if the replica answered its last health check", labels=["replica"])
        streaming = GaugeMetricFamily(
            "armory_front_replica_robots", "Robots streaming on the replica, as it last reported", labels=["replica"]
        )
        pending = GaugeMetricFamily(
            "armory_front_replica_pending", "Robots placed on the replica that it has not reported streaming yet", labels=["replica"]
        )
        capacity = GaugeMetricFamily("armory_front_replica_max_robots", "The replica's --max_robots", labels=["replica"])
        for rid, healthy, n_streaming, n_pending, max_robots in replicas:
            placed_f.add_metric([rid], placed.get(rid, 0))
            up.add_metric([rid], 1.0 if healthy else 0.0)
            streaming.add_metric([rid], n_streaming)
            pending.add_metric([rid], n_pending)
            if max_robots is not None:  # known once the replica has answered
                capacity.add_metric([rid], max_robots)
        yield from (refused_f, placed_f, up, streaming, pending, capacity)
        yield CounterMetricFamily(
            "armory_front_moves", "Robots the front released from one replica to place them on another (rebalancing)", value=moves
        )


class FrontMetrics:
    """The front's registry and its HTTP endpoint."""

    def __init__(self, snapshot: Callable[[], FrontSnapshot]) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(FrontCollector(snapshot))

    def serve(self, port: int, host: str) -> tuple[int, Callable[[], None]]:
        """Start the HTTP endpoint; returns the port bound (0: a free one) and a function that stops it."""
        server, thread = start_http_server(port, addr=host, registry=self.registry)
        bound = int(server.server_address[1])

        def stop() -> None:
            server.shutdown()
            thread.join(timeout=5)

        return bound, stop

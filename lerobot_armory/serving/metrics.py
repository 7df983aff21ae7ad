"""Prometheus metrics of the server (``--metrics_port``).

Per-robot values are read from the fleet when Prometheus scrapes (a custom collector), so the
hot paths pay nothing for them; per-batch histograms are fed by the serving loop's batch
listener. Names follow Prometheus conventions: ``armory_`` prefix, base units in the name.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from lerobot_armory.inference_latency import OnlineLatency
from lerobot_armory.serving.fleet import Fleet
from lerobot_armory.serving.loop import BatchRecord, LoopStats
from lerobot_armory.serving.swap import RESULTS, SwapResult

LATENCY_BUCKETS = (0.005, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0)
DECISION_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05)


class FleetCollector(Collector):
    """Per-robot and fleet-wide values, computed at scrape time under the fleet lock."""

    def __init__(self, fleet: Fleet, stats: LoopStats) -> None:
        self.fleet = fleet
        self.stats = stats

    def collect(self) -> Iterator:
        labels = ["robot_id", "tier"]
        starvation = GaugeMetricFamily("armory_robot_starvation_ratio", "Starved / all ticks, from the robot's execution reports", labels=labels)
        executed = CounterMetricFamily("armory_robot_executed_steps", "Steps the robot executed (reported)", labels=labels)
        starved = CounterMetricFamily("armory_robot_starved_steps", "Ticks the robot starved (reported)", labels=labels)
        served = CounterMetricFamily("armory_robot_chunks_served", "Chunks sent to the robot", labels=labels)
        rejected = CounterMetricFamily("armory_robot_observations_rejected", "Observations refused (malformed, rate)", labels=labels)
        clamped = CounterMetricFamily(
            "armory_robot_index_claims_cut",
            "Observations whose action index ran ahead of what the robot can have executed (cut to the bound)",
            labels=labels,
        )
        obs_age = GaugeMetricFamily("armory_robot_observation_age_seconds", "Age of the latest observation held for the robot", labels=labels)
        chunk_age = GaugeMetricFamily("armory_robot_last_chunk_age_seconds", "Time since the robot's last chunk was sent", labels=labels)
        # Timestamp exchanges measure the round trip only; how it splits into uplink and downlink
        # is not observable (DelayEstimator), so no per-direction gauge is published: two would
        # always show the same half and suggest a measurement that does not exist.
        round_trip = GaugeMetricFamily(
            "armory_robot_round_trip_seconds",
            "Network round trip robot-server-robot, from timestamp exchanges (server hold time excluded)",
            labels=labels,
        )
        one_way = GaugeMetricFamily(
            "armory_robot_one_way_delay_seconds",
            "Half the estimated round trip: the delay assumed each way (the uplink/downlink split is not observable)",
            labels=labels,
        )
        weight = GaugeMetricFamily("armory_robot_weight", "Scheduling weight from the registration", labels=labels)
        with self.fleet.cond:
            now = self.fleet.clock()
            sessions = self.fleet.active()
            for s in sessions:
                lv = [s.robot_id, s.spec.tier]
                starvation.add_metric(lv, s.counters.reported_starvation_pct / 100.0)
                executed.add_metric(lv, s.counters.reported_executed)
                starved.add_metric(lv, s.counters.reported_starved)
                served.add_metric(lv, s.counters.chunks_sent)
                rejected.add_metric(lv, s.counters.rejected)
                clamped.add_metric(lv, s.mirror.clamped_indices)
                obs_age.add_metric(lv, now - s.mirror.obs_recv if s.mirror.obs_index is not None else float("nan"))
                chunk_age.add_metric(lv, now - s.counters.last_chunk_time if s.counters.last_chunk_time is not None else float("nan"))
                round_trip.add_metric(lv, s.mirror.estimator.round_trip_s)
                one_way.add_metric(lv, s.mirror.estimator.one_way_s)
                weight.add_metric(lv, s.spec.weight)
            connected = len(sessions)
            evicted = self.fleet.evicted_idle
        yield from (starvation, executed, starved, served, rejected, clamped, obs_age, chunk_age, round_trip, one_way, weight)
        yield GaugeMetricFamily("armory_robots_connected", "Robots with an open stream", value=connected)
        yield CounterMetricFamily(
            "armory_sessions_evicted_idle", "Streaming sessions that sent nothing and gave their slot to a newcomer", value=evicted
        )
        yield CounterMetricFamily("armory_device_busy_seconds", "Time the device spent on batches", value=self.stats.busy_s)
        yield CounterMetricFamily(
            "armory_device_idle_with_work_seconds", "Time the device sat idle while a useful request waited", value=self.stats.idle_with_work_s
        )
        yield CounterMetricFamily("armory_batches_failed", "Batches whose inference raised", value=self.stats.failed_batches)
        yield CounterMetricFamily(
            "armory_batches_out_of_memory", "Batches that ran out of device memory (each lowered the batch cap)", value=self.stats.oom_batches
        )
        yield CounterMetricFamily(
            "armory_batches_unrecorded",
            "Batches served without the CUDA graph meant for them (correct chunks at eager speed; the log says why)",
            value=self.stats.unrecorded_batches,
        )
        if self.stats.batch_cap is not None:
            yield GaugeMetricFamily("armory_batch_cap", "The batch cap after out-of-memory batches lowered it", value=self.stats.batch_cap)


class LatencyCollector(Collector):
    """The scheduler's ``d_infer(b)`` table and its drift from the start-up profile, per batch size."""

    def __init__(self, latency: OnlineLatency) -> None:
        self.latency = latency

    def collect(self) -> Iterator:
        labels = ["batch_size"]
        estimate = GaugeMetricFamily("armory_latency_estimate_seconds", "d_infer(b) the scheduler uses now", labels=labels)
        startup = GaugeMetricFamily("armory_latency_startup_seconds", "d_infer(b) of the start-up profile", labels=labels)
        drift = GaugeMetricFamily("armory_latency_drift_ratio", "(current - start-up) / start-up d_infer(b)", labels=labels)
        for d in self.latency.drift():
            lv = [str(d.batch_size)]
            estimate.add_metric(lv, d.current_ms / 1000.0)
            startup.add_metric(lv, d.startup_ms / 1000.0)
            drift.add_metric(lv, d.pct / 100.0)
        yield from (estimate, startup, drift)


class ServerMetrics:
    """The registry, its histograms, and the batch listener that feeds them."""

    def __init__(self, fleet: Fleet, stats: LoopStats, max_batch_size: int, latency: OnlineLatency | None = None) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(FleetCollector(fleet, stats))
        if latency is not None:
            self.registry.register(LatencyCollector(latency))
        self.batch_size = Histogram(
            "armory_batch_size", "Robots per dispatched batch", buckets=tuple(range(1, max_batch_size + 1)), registry=self.registry
        )
        self.inference = Histogram(
            "armory_inference_seconds", "Batch inference time by batch size", ["batch_size"], buckets=LATENCY_BUCKETS, registry=self.registry
        )
        self.decision = Histogram(
            "armory_scheduler_decision_seconds", "Time the scheduler took to pick a batch", buckets=DECISION_BUCKETS, registry=self.registry
        )

        self.swaps = Counter(
            "armory_policy_swaps", "Live policy swaps asked by an operator, by result", ["result"], registry=self.registry
        )
        for result in RESULTS:
            self.swaps.labels(result=result)  # every result shows, 0 until it happens
        self.swap_seconds = Gauge(
            "armory_policy_swap_seconds", "Duration of the last successful swap (load + warm-up + profile + switch)", registry=self.registry
        )
        self.policy = Gauge(
            "armory_policy_info",
            "The checkpoints served now (value 1 each; labels: the policy's name and its path)",
            ["policy", "path"],
            registry=self.registry,
        )
        # Several policies on one device (--policies): what each one's batches took.
        self.policy_batches = Counter("armory_policy_batches", "Batches run, by policy", ["policy"], registry=self.registry)
        self.policy_device = Counter(
            "armory_policy_device_seconds", "Device time of the batches run, by policy", ["policy"], registry=self.registry
        )

    def set_policy(self, policy: str, path: str, replaces: str | None = None) -> None:
        """Policy ``policy`` serves ``path`` now (in place of ``replaces``, if given; other
        policies' samples stay, even where two serve the same path)."""
        if replaces is not None and replaces != path:
            try:
                self.policy.remove(policy, replaces)
            except KeyError:
                pass  # not shown (yet): nothing to take down
        self.policy.labels(policy=policy, path=path).set(1)

    def on_swap(self, result: SwapResult, policy: str) -> None:
        """A swap of ``policy`` ended with ``result``."""
        self.swaps.labels(result=result.result).inc()
        if result.ok:
            self.swap_seconds.set(result.seconds)
            self.set_policy(policy, result.new_path, replaces=result.old_path)

    def on_batch(self, record: BatchRecord) -> None:
        size = len(record.robots)
        self.batch_size.observe(size)
        self.inference.labels(batch_size=str(size)).observe(record.t_end - record.t_start)
        self.decision.observe(record.decision_ms / 1000.0)
        self.policy_batches.labels(policy=record.policy).inc()
        self.policy_device.labels(policy=record.policy).inc(max(0.0, record.t_end - record.t_start))

    def serve(self, port: int, host: str) -> tuple[int, Callable[[], None]]:
        """Start the HTTP endpoint; returns the port it bound (``port=0``: a free one, picked by
        the OS) and a function that stops it."""
        server, thread = start_http_server(port, addr=host, registry=self.registry)
        bound = int(server.server_address[1])

        def stop() -> None:
            server.shutdown()
            thread.join(timeout=5)

        return bound, stop


def status_line(fleet: Fleet, stats: LoopStats, learning: OnlineLatency | None) -> str:
    """One line of fleet status (the server logs it every second): robots, batches, mean batch
    size, device busy share, starvation by tier, decision p99, mirror error, idle-with-work time,
    failed batches, and the learnt ``d_infer``'s drift (``learning``; None: the table is fixed)."""
    with fleet.cond:
        sessions = fleet.active()
        tiers: dict[str, list[float]] = {}
        for s in sessions:
            tiers.setdefault(s.spec.tier, []).append(s.counters.reported_starvation_pct)
        errors = [s.counters.index_error for s in sessions if s.counters.index_error is not None]
    sizes = stats.batch_sizes
    total = sum(sizes.values())
    mean_b = sum(k * v for k, v in sizes.items()) / total if total else 0.0
    elapsed = max(1e-9, fleet.clock() - stats.started)
    tier_txt = " ".join(f"{t} {statistics.mean(v):.1f}%" for t, v in sorted(tiers.items())) or "-"
    dec = sorted(stats.decision_ms)
    p99 = dec[min(len(dec) - 1, int(0.99 * len(dec)))] if dec else 0.0
    if learning is not None:
        worst = learning.max_drift()
        latency_txt = f"d_infer_drift={worst.pct:+.0f}%@b={worst.batch_size}"
    else:
        latency_txt = "d_infer=fixed"
    return (
        f"robots={len(sessions)} batches={stats.batches} mean_b={mean_b:.2f} busy={100 * stats.busy_s / elapsed:.0f}% "
        f"starvation[{tier_txt}] decision_p99={p99:.2f}ms mirror_err={max(errors) if errors else '-'} "
        f"idle_with_work={stats.idle_with_work_s * 1000:.0f}ms failed={stats.failed_batches} {latency_txt}"
        + (f" batch_cap={stats.batch_cap} (lowered after {stats.oom_batches} out-of-memory batches)" if stats.batch_cap is not None else "")
        + (f" unrecorded={stats.unrecorded_batches} (batches without their CUDA graph)" if stats.unrecorded_batches else "")
    )

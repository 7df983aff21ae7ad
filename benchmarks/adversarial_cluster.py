"""The cluster front under attack: a registration flood, and registrations that lie and never stream.

Each row starts a cluster in a process of its own (``serve``: two in-process replicas of the
analytic planner, batches taking the H100 π0.5 profile's time, EDF, b = 3, room for 64 robots
each, and the front over them, health checks every 0.25 s), honest ``armory_sim`` robots in this
process (20 fps; fast: h_max 6, slow: h_max 10; the real client, which retries with its back-off),
and the attacker. Honest robots register through a local TCP proxy whose upstream side is bound
to 127.0.0.2, so that the front sees them as another host than the attacker (127.0.0.1): an
attacker and the robots it locks out do not share a host.

Rows:

- ``front_register_flood``: 2 honest robots stream, then one process sends 3,000 registrations
  with fresh ids, valid features and no stream, through the front, as fast as 8 threads get
  answers. 2 honest newcomers start 0.5 s and 4 s after the flood's first registration (the
  second after the flood if it is over by then), 2 more when it ends. Passes when every
  newcomer executes its first action within ``JOIN_LIMIT_S`` of its start, no honest robot
  failed (the incumbents' starvation is reported), the front is up at the end (process alive, gRPC health SERVING), no
  robot was told ``no replica is up`` while both replicas were up, and the front counted its
  refusals by reason (at least as many of each as the attacker saw).
- ``front_register_flood_hosts``: the same flood from 8 addresses (127.0.0.10-17), as an attacker
  with several hosts (or an IPv6 prefix) sends it: each address has its own per-host budget at
  the front, and every registration reaches a replica from the front's own address (since the
  front proves each robot's host to the replicas, they count that host: serving/forwarding.py).
  Same test.
- ``front_lying_registrations``: 4 honest robots stream; from 2 s on, one registration a second
  that lies (fps 1000 and h_max 1, then fps 20 and h_max 1, alternately, fresh ids) and never
  opens its stream; honest newcomers join at 4 s and 8 s, at the same instants as two of the lies
  (joins are what makes the front plan a move). Passes when no honest robot is moved (the front's moves, and no ``MOVED`` notice), at
  most one move was made per ``MOVE_INTERVAL_S``, the front is up and every honest robot ran.
  ``--no_attacker`` runs the same honest robots alone (the control: they need no move).

``--tree=PATH`` runs the cluster from another checkout (``PYTHONPATH=PATH``; the robots and the
attacker are this tree's: the protocol is the same), for the before column. Prints a table, writes
``results.json`` and ``README.md`` to ``--output_dir``, exits 1 if a row fails.

    .venv/bin/python benchmarks/adversarial_cluster.py                       # the three rows, ~1.5 min
    .venv/bin/python benchmarks/adversarial_cluster.py --rows=front_register_flood --tree=../before
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

ROWS = ("front_register_flood", "front_register_flood_hosts", "front_lying_registrations")
JOIN_LIMIT_S = 3.0  # a newcomer's start -> its first executed action
MOVE_INTERVAL_S = 5.0  # the front's least time between two moves (checked with the poll's resolution)
POLL_S = 0.25
MARK = "@@armory-serve "  # the serve process's answers (anything else on its stdout is a library's)
HONEST_HOST = "127.0.0.2"
FLOOD_COUNT = 3000
FLOOD_THREADS = 8
DURING_S = (0.5, 4.0)  # newcomers start this long after the flood's first registration (the second may be after it)
FLOOD_HOSTS = 8  # front_register_flood_hosts: the flood leaves from 127.0.0.10 ... 127.0.0.17
LIES = ((1000.0, 0, 1), (20.0, 0, 1))  # (fps, h_min, h_max) asked, alternately


# ---- the cluster process (``serve``): runs on whichever tree PYTHONPATH names --------------------


def serve(planner: str) -> None:
    """Two in-process replicas and a front; one JSON line when up, then one per ``status`` line on
    stdin, until ``stop``. Only APIs the cluster had before issue 33 are required."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    import lerobot_armory
    from lerobot_armory.engine.options import EngineOptions, PolicyOptions
    from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
    from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
    from lerobot_armory.entrypoints.server import ServerConfig
    from lerobot_armory.schedulers import EarliestDeadlineConfig

    def config() -> ServerConfig:
        return ServerConfig(
            policy=PolicyOptions(planner, "cpu"), engine=EngineOptions(emulate_profile="h100-pi05"),
            scheduler=EarliestDeadlineConfig(), max_batch_size=3, status_interval_s=0.0, log_level="warning", port=0,
        )  # fmt: skip

    replicas = LocalReplicas({f"r{k}": ArmoryReplica(config(), f"r{k}") for k in range(2)})
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.25)))
    logging.getLogger("lerobot_armory.entrypoints.cluster.front").setLevel(logging.INFO)
    metrics_port = front.serve_metrics(0) if hasattr(front, "serve_metrics") else None
    deadline = time.monotonic() + 30
    while not all(s.view.healthy for s in front.front.state.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    hello = {
        "front": front.address, "metrics_port": metrics_port, "tree": str(Path(lerobot_armory.__file__).parent.parent),
        "replicas": {rid: s.address for rid, s in front.front.state.items()},
        "max_robots": {rid: s.view.max_robots for rid, s in front.front.state.items()},
    }  # fmt: skip
    print(MARK + json.dumps(hello), flush=True)
    channel = grpc.insecure_channel(front.address)
    health = health_pb2_grpc.HealthStub(channel)
    for line in sys.stdin:
        if line.strip() == "stop":
            break
        f = front.front
        with f.lock:
            status = {
                "t": time.monotonic(),
                "refused": dict(f.refused) if hasattr(f, "refused") else None,
                "moves": [[m.robot_id, m.source, m.target] for m in f.moves],
                "healthy": {rid: s.view.healthy for rid, s in f.state.items()},
                "reported": {rid: sorted(s.reported) for rid, s in f.state.items()},
                "pending": {rid: len(s.pending) for rid, s in f.state.items()},
            }
        try:
            answer = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=2)
            status["front_serving"] = answer.status == health_pb2.HealthCheckResponse.SERVING
        except grpc.RpcError as exc:
            status["front_serving"] = False
            status["front_health_error"] = f"{exc.code().name}: {exc.details()}"
        print(MARK + json.dumps(status), flush=True)
    channel.close()
    front.stop(0)
    for rid in replicas.ids():
        replicas.kill(rid)


class Cluster:
    """The ``serve`` process, driven over its stdin/stdout; its log goes to ``log``."""

    def __init__(self, planner: str, tree: Path, log: Path) -> None:
        env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONUNBUFFERED": "1"}
        self.log = log
        self._log_file = log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "serve", planner], cwd=str(tree), env=env,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log_file, text=True,
        )  # fmt: skip
        hello = self._answer()
        if hello is None:
            self.proc.wait(timeout=10)
            raise RuntimeError(f"the cluster did not start (exit {self.proc.returncode}):\n{log.read_text()[-3000:]}")
        self.hello = hello
        self._lock = threading.Lock()
        self.statuses: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll, daemon=True)
        self._poller.start()

    def _answer(self) -> dict[str, Any] | None:
        """The serve process's next answer (other stdout lines skipped); None when it ended."""
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith(MARK):
                return json.loads(line[len(MARK) :])
        return None

    @property
    def front(self) -> str:
        return self.hello["front"]

    def status(self) -> dict[str, Any] | None:
        with self._lock:
            if self.proc.poll() is not None:
                return None
            try:
                assert self.proc.stdin is not None and self.proc.stdout is not None
                self.proc.stdin.write("status\n")
                self.proc.stdin.flush()
                return self._answer()
            except (OSError, ValueError):
                return None

    def _poll(self) -> None:
        while not self._stop.wait(POLL_S):
            s = self.status()
            if s is None:
                return
            self.statuses.append(s)

    def metrics(self) -> dict[str, float] | None:
        """The front's ``armory_front_registrations_refused_total`` by reason (None: no endpoint)."""
        port = self.hello.get("metrics_port")
        if not port:
            return None
        import urllib.request

        from prometheus_client.parser import text_string_to_metric_families

        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
        return {
            s.labels["reason"]: s.value
            for fam in text_string_to_metric_families(text)
            for s in fam.samples
            if s.name == "armory_front_registrations_refused_total"
        }

    def stop(self) -> int | None:
        self._stop.set()
        self._poller.join(timeout=5)
        with self._lock:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.write("stop\n")
                self.proc.stdin.flush()
            except (OSError, ValueError):
                pass
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log_file.close()
        return self.proc.returncode


# ---- the flood process (``flood``) -----------------------------------------------------------------


def flood(target: str, count: int, threads: int, features_json: str, hosts: int = 1) -> None:
    """``count`` registrations with fresh ids and no stream to ``target`` from ``threads`` threads
    (``hosts`` > 1: through proxies leaving from that many loopback addresses, 127.0.0.10 on);
    prints ``START <monotonic>`` at the first, then one JSON line of what came back."""
    import grpc

    from lerobot_armory.proto import armory_pb2 as pb
    from lerobot_armory.proto.armory_pb2_grpc import ArmoryStub

    features = [pb.TensorSpec(name=n, dtype=d, shape=list(s)) for n, (d, s) in json.loads(features_json).items()]
    lock = threading.Lock()
    nxt = iter(range(count))
    outcomes: Counter = Counter()
    samples: dict[str, str] = {}
    started = threading.Event()
    t0 = time.monotonic()

    proxies = [SourceProxy(target, f"127.0.0.{10 + h}") for h in range(hosts)] if hosts > 1 else []
    targets = [p.address for p in proxies] or [target]

    def run(k: int) -> None:
        channel = grpc.insecure_channel(targets[k % len(targets)])
        stub = ArmoryStub(channel)
        while True:
            with lock:
                k = next(nxt, None)
            if k is None:
                break
            request = pb.RegisterRequest(
                robot_id=f"flood-{k}", fps=20.0, h_min=1, h_max=10, weight=1.0, tier="slow", features=features,
                client_send_time=time.monotonic(),
            )  # fmt: skip
            if not started.is_set():
                with lock:
                    if not started.is_set():
                        print(f"START {time.monotonic()}", flush=True)
                        started.set()
            try:
                stub.Register(request, timeout=5)
                key = "OK"
            except grpc.RpcError as exc:
                key = classify(exc.code().name, exc.details() or "")
                with lock:
                    samples.setdefault(key, f"{exc.code().name}: {(exc.details() or '')[:200]}")
            with lock:
                outcomes[key] += 1
        channel.close()

    workers = [threading.Thread(target=run, args=(k,), daemon=True) for k in range(max(threads, hosts))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    print(json.dumps({"outcomes": dict(outcomes), "samples": samples, "elapsed_s": time.monotonic() - t0, "end": time.monotonic()}), flush=True)


def classify(code: str, details: str) -> str:
    """A refusal as the front's reasons name it: rate, replica_rate, full, unavailable, down (else the code)."""
    if "take no more registrations through this front" in details or ("too many registrations" in details and "replica is full" in details):
        return "replica_rate"
    if "too many registrations" in details:
        return "rate"
    if code == "RESOURCE_EXHAUSTED":
        return "full"
    if "no replica is up" in details:
        return "down"
    if code == "UNAVAILABLE":
        return "unavailable"
    return code


# ---- honest robots (this process) -------------------------------------------------------------------


class SourceProxy:
    """TCP proxy on 127.0.0.1 to ``target`` whose upstream connections leave from ``source``: the
    honest robots' registrations reach the front from another host than the attacker's."""

    def __init__(self, target: str, source: str = HONEST_HOST) -> None:
        host, _, port = target.rpartition(":")
        self.target = (host, int(port))
        self.source = source
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.address = f"127.0.0.1:{self.listener.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.socket()
            try:
                upstream.bind((self.source, 0))
                upstream.connect(self.target)
            except OSError:
                client.close()
                upstream.close()
                continue
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self.listener.close()


class RefusalLog(logging.Handler):
    """What the honest clients were told while retrying (their back-off warnings), by reason."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.seen: Counter = Counter()
        self.samples: dict[str, str] = {}

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if "busy or not ready:" not in text:
            return
        told = text.split("busy or not ready:", 1)[1].strip()
        code, _, details = told.partition(":")
        key = classify(code.strip(), details)
        self.seen[key] += 1
        self.samples.setdefault(key, told[:200])


class Honest:
    """One armory_sim robot (the real client) ticking on a thread from ``start()`` until ``end``
    (a monotonic time), connected or not (``run_ticks``' loop: ticks before it is served starve)."""

    def __init__(self, address: str, robot_id: str, fast: bool, seed: int) -> None:
        from tests.support import adversaries as adv
        from tests.support.cluster import sim_robot

        self.robot_id = robot_id
        self.sim = sim_robot(address, robot_id, fast=fast, seed=seed)
        self.started_at: float | None = None
        self.timeline = adv.Timeline()
        self.end = float("inf")
        self.thread = threading.Thread(target=self._run, name=f"honest-{robot_id}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        client, tl = self.sim.client, self.timeline

        def connect() -> None:
            try:
                client.connect()
            except Exception as exc:  # noqa: BLE001 - refused or unreachable: the robot starves
                client.fatal = exc

        self.sim.robot.connect()
        self.started_at = start = time.monotonic()
        threading.Thread(target=connect, name=f"connect-{self.robot_id}", daemon=True).start()
        period = 1.0 / client.identity.fps
        next_tick = last_report = start
        try:
            while (now := time.monotonic()) < self.end:
                if now < next_tick:
                    time.sleep(min(next_tick - now, 0.05))
                    continue
                tl.times.append(round(now - start, 4))
                tl.executed.append(1 if client.step() else 0)
                tl.chunks.append(client.chunks_received)
                if tl.first_chunk_s is None and client.chunks_received:
                    tl.first_chunk_s = round(now - start, 4)
                if now - last_report >= 0.2:
                    client.report()
                    last_report = now
                next_tick += period
                if time.monotonic() - next_tick > period:  # overran: no burst to catch up
                    next_tick = time.monotonic()
        finally:
            client.close()
            self.sim.robot.disconnect()

    def stop_at(self, end: float) -> None:
        self.end = end

    def result(self, t0: float) -> dict[str, Any]:
        self.thread.join(timeout=max(0.0, self.end - time.monotonic()) + 30)
        client, tl = self.sim.client, self.timeline
        moved = [n for n in client.notices if "moved" in n.lower()]
        tl = tl if tl.times else None
        return {
            "robot_id": self.robot_id,
            "start_s": None if self.started_at is None else round(self.started_at - t0, 3),
            "first_chunk_s": None if tl is None else tl.first_chunk_s,
            "starvation_pct": None if tl is None or tl.first_chunk_s is None else tl.starvation_pct(tl.first_chunk_s),
            "chunks": client.chunks_received,
            "reconnects": client.reconnects,
            "moved_notices": len(moved),
            "error": f"{type(client.fatal).__name__}: {client.fatal}" if client.fatal is not None else None,
        }


# ---- the rows ---------------------------------------------------------------------------------------


def wire_features() -> dict[str, tuple[str, tuple[int, ...]]]:
    from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
    from lerobot_armory.robot.features import FeatureMap
    from tests.support.cluster import IMAGE

    robot = ArmorySim(ArmorySimConfig(scene="static", image_size=IMAGE, seed=0))
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    return {name: (dtype, tuple(shape)) for name, (dtype, shape) in fmap.wire_features().items()}


def run_flood(cluster: Cluster, proxy: SourceProxy, attack: bool, hosts: int = 1) -> dict[str, Any]:
    """2 honest robots stream; the flood; newcomers DURING_S after its start and 2 when it ends; all run 6 s more."""
    t0 = time.monotonic()
    tail_s = 6.0
    incumbents = [Honest(proxy.address, f"honest{k}", fast=k == 0, seed=k) for k in range(2)]
    during = [Honest(proxy.address, f"during{k}", fast=k == 0, seed=10 + k) for k in range(2)]
    after = [Honest(proxy.address, f"after{k}", fast=k == 0, seed=20 + k) for k in range(2)]
    for h in incumbents:
        h.start()
    time.sleep(2.0)
    record: dict[str, Any] = {}
    if attack:
        proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "flood", cluster.front, str(FLOOD_COUNT), str(FLOOD_THREADS),
             json.dumps(wire_features()), str(hosts)],
            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
        assert proc.stdout is not None
        first = proc.stdout.readline()
        if not first.startswith("START"):
            raise RuntimeError(f"the flood did not start: {first!r}")
        flood_start = float(first.split()[1])
        timers = [threading.Timer(max(0.0, flood_start + delay - time.monotonic()), h.start) for h, delay in zip(during, DURING_S, strict=True)]
        for timer in timers:
            timer.start()
        result = json.loads(proc.stdout.readline())
        proc.wait(timeout=30)
        record["flood"] = {**result, "start_s": flood_start - t0, "end_s": result["end"] - t0}
    else:
        time.sleep(1.0)
        for h in during:
            h.start()
        time.sleep(3.0)
    for h in after:
        h.start()
    if attack:
        for timer in timers:
            timer.join()
    end = time.monotonic() + tail_s
    record["honest_end_t"] = end
    for h in incumbents + during + after:
        h.stop_at(end)
    record["honest"] = [h.result(t0) for h in incumbents + during + after]
    return record


def run_lies(cluster: Cluster, proxy: SourceProxy, attack: bool) -> dict[str, Any]:
    from lerobot_armory.robot.connection import Connection

    t0 = time.monotonic()
    end_s = 14.0
    honest = [Honest(proxy.address, f"honest{k}", fast=k % 2 == 0, seed=k) for k in range(4)]
    newcomers = {4.0: Honest(proxy.address, "newcomer0", fast=True, seed=10),
                 8.0: Honest(proxy.address, "newcomer1", fast=False, seed=11)}  # fmt: skip
    for h in [*honest, *newcomers.values()]:
        h.stop_at(t0 + end_s)
    for h in honest:
        h.start()
    lies: Counter = Counter()
    samples: dict[str, str] = {}
    features = wire_features()
    k = 0
    pending = sorted(newcomers)
    next_lie = 2.0
    while time.monotonic() - t0 < end_s - 2.0:
        now = time.monotonic() - t0
        if pending and now >= pending[0]:
            newcomers[pending.pop(0)].start()
        if attack and now >= next_lie:
            fps, h_min, h_max = LIES[k % len(LIES)]
            conn = Connection(cluster.front)
            what = f"fps {fps:g} h_max {h_max}"
            try:
                conn.register(f"liar-{k}", features, fps, h_min, h_max)
                lies[f"{what}: granted"] += 1
            except Exception as exc:  # noqa: BLE001 - a refusal is an outcome
                code = getattr(exc, "code", lambda: None)()
                key = f"{what}: {code.name if code is not None else type(exc).__name__}"
                lies[key] += 1
                samples.setdefault(key, (getattr(exc, "details", lambda: str(exc))() or "")[:200])
            finally:
                conn.close()  # never streams
            k += 1
            next_lie += 1.0
        time.sleep(0.02)
    return {"honest_end_t": t0 + end_s, "lies": dict(lies), "lie_samples": samples, "honest": [h.result(t0) for h in honest + list(newcomers.values())]}


def judge(row: str, record: dict[str, Any], statuses: list[dict[str, Any]], metrics: dict[str, float] | None, attack: bool) -> dict[str, Any]:
    failures: list[str] = []
    notes: list[str] = []
    last = statuses[-1] if statuses else {}
    up = bool(record.get("cluster_alive") and last.get("front_serving"))
    if not up:
        failures.append("front down at the end" + (f": {last.get('front_health_error')}" if last.get("front_health_error") else ""))
    honest = record.get("honest", [])
    errors = [f"{h['robot_id']}: {h['error']}" for h in honest if h["error"]]
    if errors:
        failures.append("honest robot failed: " + "; ".join(e[:160] for e in errors[:2]))
    moves = last.get("moves", [])
    # When each move first showed in the polled status; those after the honest robots began to
    # stop (the end of the run: a replica emptied by robots leaving) are not the attack's doing.
    seen_at: list[float] = []
    for s in statuses:
        seen_at += [s["t"]] * (len(s["moves"]) - len(seen_at))
    end = record.get("honest_end_t", float("inf"))
    during = [m for m, t in zip(moves, seen_at, strict=False) if t < end]
    summary: dict[str, Any] = {"row": row, "attacker": attack, "front_up": up, "moves": moves, "moves_during_run": during}
    honest_ids = {h["robot_id"] for h in honest}
    moved = sorted({m[0] for m in during if m[0] in honest_ids} | {h["robot_id"] for h in honest if h["moved_notices"]})
    summary["honest_moved"] = moved
    if row.startswith("front_register_flood"):
        newcomers = [h for h in honest if not h["robot_id"].startswith("honest")]
        joins = {h["robot_id"]: h["first_chunk_s"] for h in newcomers}
        summary["join_s"] = joins
        late = [f"{rid} {'never' if j is None else f'{j:.1f} s'}" for rid, j in joins.items() if j is None or j > JOIN_LIMIT_S]
        if late:
            failures.append(f"newcomers not served within {JOIN_LIMIT_S:g} s: {', '.join(late)}")
        summary["incumbent_starvation_pct"] = {h["robot_id"]: h["starvation_pct"] for h in honest if h["robot_id"].startswith("honest")}
        told = Counter(record.get("honest_told", {}))
        flood = record.get("flood", {})
        seen = Counter({k: v for k, v in flood.get("outcomes", {}).items() if k != "OK"})
        summary["flood"] = {k: flood.get(k) for k in ("outcomes", "elapsed_s", "samples")}
        summary["honest_told"] = dict(told)
        refused = last.get("refused")
        summary["front_refused"] = refused
        summary["front_metrics_refused"] = metrics
        both_up = all(all(s["healthy"].values()) for s in statuses) if statuses else False
        summary["replicas_up_throughout"] = both_up
        down = seen["down"] + told["down"]
        if both_up and down:
            failures.append(f"{down} registrations told 'no replica is up' while both replicas were up")
        if refused is None:
            failures.append("the front counts no refusal")
        else:
            short = {r: (n, refused.get(r, 0)) for r, n in seen.items() if refused.get(r, 0) < n}
            if short:
                failures.append("front counted fewer refusals than the attacker saw: " + ", ".join(f"{r} {c} < {n}" for r, (n, c) in short.items()))
            if metrics is not None and any(metrics.get(r, 0) != v for r, v in refused.items()):
                failures.append(f"metrics {metrics} differ from the front's counters {refused}")
        if flood:
            notes.append(
                f"{sum(flood['outcomes'].values())} registrations in {flood['elapsed_s']:.1f} s: "
                + ", ".join(f"{k} {v}" for k, v in sorted(flood["outcomes"].items()))
            )
        notes.append("newcomers' first action " + ", ".join(f"{rid} {'-' if j is None else f'{j:.1f} s'}" for rid, j in joins.items()))
        if told:
            notes.append("honest robots told " + ", ".join(f"{k} x{v}" for k, v in sorted(told.items())))
        if refused is not None:
            notes.append("front counted " + (", ".join(f"{k} {v}" for k, v in sorted(refused.items())) or "no refusal"))
        notes.append(f"front logged {record.get('front_log_refusal_lines', 0)} refusal line(s)")
        notes.append(f"honest robots moved during the run: {', '.join(moved) or 'none'}")
    else:
        summary["lies"] = record.get("lies")
        if moved:
            failures.append(f"honest robots moved: {', '.join(moved)}")
        # At most one move per MOVE_INTERVAL_S (with the poll's resolution).
        gaps = [b - a for a, b in zip(seen_at, seen_at[1:], strict=False)]
        summary["move_gaps_s"] = gaps
        if any(g < MOVE_INTERVAL_S - 2 * POLL_S for g in gaps):
            failures.append(f"moves {min(gaps):.1f} s apart (at most one per {MOVE_INTERVAL_S:g} s)")
        notes.append(f"{len(during)} move(s) during the run" + (": " + ", ".join(f"{r} {s}->{t}" for r, s, t in during) if during else ""))
        if len(moves) > len(during):
            notes.append(f"{len(moves) - len(during)} more as the robots stopped")
        if record.get("lies"):
            notes.append("lies: " + ", ".join(f"{k} x{v}" for k, v in sorted(record["lies"].items())))
    starv = [h["starvation_pct"] for h in honest if h["starvation_pct"] is not None]
    summary["honest_starvation_pct_mean"] = sum(starv) / len(starv) if starv else None
    summary["passed"] = not failures
    summary["failures"] = failures
    summary["notes"] = notes
    return summary


def run_row(row: str, planner: str, tree: Path, work: Path, attack: bool) -> tuple[dict[str, Any], dict[str, Any]]:
    cluster = Cluster(planner, tree, work / f"{row}-cluster.log")
    proxy = SourceProxy(cluster.front)
    told = RefusalLog()
    client_log = logging.getLogger("lerobot_armory.robot.client")
    client_log.addHandler(told)
    record: dict[str, Any] = {"hello": cluster.hello}
    metrics = None
    try:
        time.sleep(0.5)
        record["t0"] = time.monotonic()
        if row == "front_register_flood":
            record.update(run_flood(cluster, proxy, attack))
        elif row == "front_register_flood_hosts":
            record.update(run_flood(cluster, proxy, attack, hosts=FLOOD_HOSTS))
        else:
            record.update(run_lies(cluster, proxy, attack))
        time.sleep(2 * POLL_S)
        record["cluster_alive"] = cluster.proc.poll() is None
        try:
            metrics = cluster.metrics()
        except OSError as exc:
            record["metrics_error"] = str(exc)
    finally:
        client_log.removeHandler(told)
        record["honest_told"] = dict(told.seen)
        record["honest_told_samples"] = told.samples
        proxy.close()
        record["cluster_exit"] = cluster.stop()
    log_text = cluster.log.read_text(errors="replace")
    record["front_log_refusal_lines"] = log_text.count("registration refused")
    record["front_log_tail"] = log_text.splitlines()[-12:]
    record["statuses_last"] = cluster.statuses[-1] if cluster.statuses else None
    # The front's view whenever it changed: robots streaming and registrations pending per replica, moves.
    changes, last = [], None
    for st in cluster.statuses:
        view = ({r: sorted(v) for r, v in st["reported"].items()}, st["pending"], len(st["moves"]), st.get("refused"))
        if view != last:
            changes.append({"t": round(st["t"] - record.get("t0", st["t"]), 2), "streaming": view[0], "pending": view[1], "moves": view[2], "refused": view[3]})
            last = view
    record["front_view"] = changes
    return record, judge(row, record, cluster.statuses, metrics, attack)


def table(rows: list[dict[str, Any]]) -> str:
    lines = [f"{'row':<28} {'front up':<9} {'result':<7} note", "-" * 100]
    for r in rows:
        name = r["row"] + ("" if r["attacker"] else " (no attacker)")
        lines.append(f"{name:<28} {'yes' if r['front_up'] else 'NO':<9} {'pass' if r['passed'] else 'FAIL':<7} {'; '.join(r['failures'] + r['notes'])}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="benchmarks/adversarial_cluster.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated of {', '.join(ROWS)}")
    ap.add_argument("--tree", default=str(ROOT), help="the checkout the cluster runs from (default: this one)")
    ap.add_argument("--output_dir", default="out/adversarial_cluster")
    ap.add_argument("--no_attacker", action="store_true", help="the honest robots alone (a control run)")
    ap.add_argument("--work_dir", default=None)
    a = ap.parse_args(argv)
    rows = [r.strip() for r in a.rows.split(",") if r.strip()]
    bad = sorted(set(rows) - set(ROWS))
    if bad:
        ap.error(f"unknown rows {bad}; known: {', '.join(ROWS)}")
    sys.path.insert(0, str(ROOT))
    logging.basicConfig(level=logging.ERROR)
    client_log = logging.getLogger("lerobot_armory.robot.client")
    client_log.setLevel(logging.WARNING)
    client_log.propagate = False  # read by RefusalLog, not printed
    from tests.support.cluster import make_planner

    work = Path(a.work_dir or tempfile.mkdtemp(prefix="armory-adversarial-cluster-"))
    work.mkdir(parents=True, exist_ok=True)
    planner = str((work / "planner").resolve())
    if not Path(planner, "config.json").is_file():
        make_planner(planner)
    tree = Path(a.tree).resolve()
    t_start = time.monotonic()
    results, records = [], []
    for row in rows:
        t0 = time.monotonic()
        record, result = run_row(row, planner, tree, work, not a.no_attacker)
        result["wall_s"] = time.monotonic() - t0
        records.append({"row": row, **record})
        results.append(result)
        print(f"{row}: {'pass' if result['passed'] else 'FAIL'} ({result['wall_s']:.0f} s) — {'; '.join(result['failures'] + result['notes'])}", flush=True)
    print()
    print(table(results))
    failed = [r for r in results if not r["passed"]]
    command = "benchmarks/adversarial_cluster.py " + " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv))
    out = Path(a.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    payload = {"command": command, "tree": str(tree), "cluster_tree": records[0]["hello"].get("tree") if records else None,
               "rows": results, "runs": records}  # fmt: skip
    (out / "results.json").write_text(json.dumps(payload, indent=1, default=str) + "\n")
    md = [
        "# The cluster front under attack", "", f"Command: `{command}` ({(time.monotonic() - t_start) / 60:.1f} min), cluster from `{tree}`.",
        "", "| row | front up | result | note |", "|---|---|---|---|",
    ]  # fmt: skip
    for r in results:
        md.append(f"| {r['row']}{'' if r['attacker'] else ' (no attacker)'} | {'yes' if r['front_up'] else '**NO**'} | "
                  f"{'pass' if r['passed'] else '**FAIL**'} | {'; '.join(r['failures'] + r['notes']).replace('|', '/')} |")  # fmt: skip
    (out / "README.md").write_text("\n".join(md) + "\n")
    print(f"\n{len(results) - len(failed)} of {len(results)} rows pass; wrote {out / 'results.json'} and {out / 'README.md'}")
    return 1 if failed else 0


if __name__ == "__main__":
    if len(sys.argv) >= 2 and sys.argv[1] == "serve":
        serve(sys.argv[2])
    elif len(sys.argv) >= 2 and sys.argv[1] == "flood":
        flood(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], int(sys.argv[6]) if len(sys.argv) > 6 else 1)
    else:
        sys.exit(main())

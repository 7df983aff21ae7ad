"""Our server side by side with LeRobot's own async inference (``policy_server`` + ``robot_client``).

The same policy directory (the demo ACT built with the chunk, bit-identical weights: both sides
load the same files) serves the same simulated robots (``armory_sim``, one process per robot on
both sides, same seeds) at fps 30, chunk H (``--chunk``, 10 by default), a new request after H/2
executed steps (5 of 10), for N robots:

- ``ours``: one ``lerobot-armory-server`` (default scheduler: lookahead) and N armory clients
  (``--fps=30 --h_min=H/2 --h_max=H``), optionally at several ``--policy.cpu_threads``;
- ``stock``: N stock ``policy_server`` processes (a stock server serves one client: a second
  client's ``Ready`` resets it), each with one stock ``robot_client`` whose robot is armory_sim
  (``actions_per_chunk=H``, ``chunk_size_threshold=0.5``, ``fps=30``, ``policy_type`` from the
  policy's ``config.json``),
  with its default observation-similarity filter;
- ``stock_nofilter``: the same with the filter patched off in the launcher.

Per system and N: per-robot starvation (mean, max over robots; counted from each robot's first
chunk, or its ``--settle_chunks``-th), control ticks/s, chunks/s per robot, chunk latency p50/p90 (observation capture -> chunk
received), total server RSS (sum over server processes, peak over the run), server CPU (% of one
core), the robot processes' CPU and the time the fleet took to become ready (servers up, robots
connected: stock loads its policy then). ``--stock_shared_server`` adds a check that two stock
clients on ONE stock server receive each other's chunks. Writes ``<device>.md`` and ``.json``
under ``--out``; exits 1 with a message if a process dies or a robot never gets a chunk.

    .venv/bin/python benchmarks/vs_lerobot_async.py --robots=1,2,4,8 --duration_s=60 \\
        --systems=ours,stock,stock_nofilter --ours_cpu_threads=1,2 --stock_shared_server \\
        --out=docs/results/vs_lerobot_async
    .venv/bin/python benchmarks/vs_lerobot_async.py --chunk=50 --robots=1 --systems=ours,stock_nofilter
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shlex
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

from lerobot_armory.bench.live import cpu_seconds, machine_cpu  # the live bench measures CPU the same way

HERE = Path(__file__).resolve().parent
FPS = 30
CHUNK = 10  # the default --chunk
THRESHOLD = 0.5  # stock: ask for a chunk when <= half of it is left (5 of 10) = after h_min_of(chunk) steps
IMAGE_SIZE = 64
SYSTEMS = ("ours", "stock", "stock_nofilter")
READY_TIMEOUT_S = 300.0
SAMPLE_S = 0.5
BUSY_PCT = 90.0


class RunFailed(RuntimeError):
    """A run could not be measured (a process died, a robot never got a chunk, ...)."""


def h_min_of(chunk: int) -> int:
    """Ours' ``--h_min`` for a chunk: the executed steps after which stock asks for the next one.

    Stock asks once ``left / chunk <= THRESHOLD``, i.e. with ``floor(chunk * THRESHOLD)`` actions
    left; ours then asks after the rest executed. For an even chunk that is ``chunk // 2`` (5 of
    10, 25 of 50); for an odd one ``chunk // 2`` would ask one step before stock does.
    """
    return chunk - math.floor(chunk * THRESHOLD)


@dataclass
class Options:
    """Command-line options (see ``parse_args``)."""

    robots: list[int]
    duration_s: float
    systems: list[str]
    device: str
    ours_cpu_threads: list[int | None]
    ours_scheduler: str
    max_batch_size: int
    stock_cpu_threads: int
    scene: str
    policy: str
    out: str | None
    work_dir: str | None
    stock_shared_server: bool
    ours_server_args: str = ""
    chunk: int = CHUNK
    settle_chunks: int = 1


@dataclass
class Variant:
    """One system as run: ``ours`` at a thread count, ``stock`` or ``stock_nofilter``."""

    system: str
    cpu_threads: int | None = None

    @property
    def label(self) -> str:
        if self.system != "ours" or self.cpu_threads is None:
            return self.system
        return f"ours ({self.cpu_threads} thread{'s' if self.cpu_threads > 1 else ''})"


@dataclass
class Proc:
    """A started process with its log file."""

    name: str
    popen: subprocess.Popen
    log: Path

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def failed(self) -> str:
        """A one-paragraph description of how this process ended, with its log's tail."""
        return f"{self.name} exited with code {self.popen.poll()}; last lines of {self.log}:\n{self.tail()}"


@dataclass
class Fleet:
    """Every process of one run."""

    servers: list[Proc] = field(default_factory=list)
    clients: list[Proc] = field(default_factory=list)
    ready_s: float = 0.0  # start -> servers up and every robot connected (``start_fleet``)

    def stop(self) -> None:
        """Terminate what is still running (each by its own pid), then reap."""
        for p in self.clients + self.servers:
            if p.popen.poll() is None:
                p.popen.send_signal(signal.SIGTERM)
        for p in self.clients + self.servers:
            try:
                p.popen.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.popen.kill()
                p.popen.wait()


# ---- processes -------------------------------------------------------------------------------


def start(name: str, cmd: list[str], log: Path, cwd: Path, env: dict[str, str] | None = None) -> Proc:
    """Start ``cmd`` with stdout and stderr to ``log``."""
    with log.open("w") as fh:
        popen = subprocess.Popen(
            cmd,
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=cwd,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
    return Proc(name, popen, log)


def free_port() -> int:
    """A TCP port free right now on loopback (the stock server cannot pick one itself)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_ours_address(proc: Proc, timeout_s: float = READY_TIMEOUT_S) -> str:
    """The address ``lerobot-armory-server`` prints once it serves."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in proc.log.read_text(errors="replace").splitlines():
            if "listening on" in line:
                return line.split("listening on")[1].strip()
        if proc.popen.poll() is not None:
            raise RunFailed(proc.failed())
        time.sleep(0.2)
    raise RunFailed(f"{proc.name} did not start within {timeout_s:.0f} s:\n{proc.tail()}")


def wait_port(proc: Proc, port: int, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Wait until ``port`` accepts connections (the stock server prints nothing reliable)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.popen.poll() is not None:
            raise RunFailed(proc.failed())
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise RunFailed(f"{proc.name} did not open port {port} within {timeout_s:.0f} s:\n{proc.tail()}")


def start_ours_server(opts: Options, threads: int | None, run_dir: Path) -> tuple[Proc, str]:
    """``lerobot-armory-server`` on a free port; returns it and its address."""
    args = [
        f"--policy.path={opts.policy}", f"--policy.device={opts.device}", "--host=127.0.0.1", "--port=0",
        f"--scheduler.type={opts.ours_scheduler}", f"--max_batch_size={opts.max_batch_size}",
        "--status_interval_s=0", "--log_level=warning",
    ]  # fmt: skip
    if threads is not None:
        args.append(f"--policy.cpu_threads={threads}")
    args += shlex.split(opts.ours_server_args)
    proc = start(
        "ours server", [sys.executable, "-m", "lerobot_armory.entrypoints.server", *args], run_dir / "server.log", run_dir
    )
    return proc, wait_ours_address(proc)


def start_stock_servers(
    opts: Options, n: int, no_filter: bool, run_dir: Path, extra: tuple[str, ...] = ()
) -> list[tuple[Proc, str]]:
    """``n`` stock policy servers, each on its own port (``extra``: more launcher options)."""
    started: list[tuple[Proc, int]] = []
    for k in range(n):
        port = free_port()
        while port in {p for _, p in started}:
            port = free_port()
        cmd = [sys.executable, str(HERE / "_stock_async.py"), "server", f"--port={port}"]
        if no_filter:
            cmd.append("--no_filter")
        if opts.stock_cpu_threads:
            cmd.append(f"--cpu_threads={opts.stock_cpu_threads}")
        cmd += extra
        started.append((start(f"stock server {k}", cmd, run_dir / f"server{k}.log", run_dir), port))
    for proc, port in started:
        wait_port(proc, port)
    return [(proc, f"127.0.0.1:{port}") for proc, port in started]


def policy_type(policy: str) -> str:
    """The policy's type as its ``config.json`` names it (the stock client must be told)."""
    return str(json.loads((Path(policy) / "config.json").read_text())["type"])


def robot_spec(opts: Options, k: int, address: str, run_dir: Path) -> dict[str, Any]:
    """What robot ``k`` needs (both sides read the keys they use)."""
    return {
        "robot_id": f"robot{k}", "scene": opts.scene, "image_size": IMAGE_SIZE, "seed": k, "fps": FPS,
        "h_min": h_min_of(opts.chunk), "h_max": opts.chunk, "actions_per_chunk": opts.chunk, "chunk_size_threshold": THRESHOLD,
        "settle_chunks": opts.settle_chunks, "address": address, "policy_path": opts.policy, "policy_type": policy_type(opts.policy), "device": opts.device,
        "duration_s": opts.duration_s, "ready_path": str(run_dir / f"ready{k}"), "go_path": str(run_dir / "go"), "stats_path": str(run_dir / f"robot{k}.json"),
    }  # fmt: skip


def start_client(system: str, spec: dict[str, Any], k: int, run_dir: Path) -> Proc:
    """Robot ``k``'s process: the armory client or the instrumented stock client."""
    path = run_dir / f"robot{k}.spec.json"
    path.write_text(json.dumps(spec))
    if system == "ours":
        cmd = [sys.executable, str(HERE / "_ours_robot.py"), str(path)]
    else:
        cmd = [sys.executable, str(HERE / "_stock_async.py"), "client", str(path)]
    return start(f"{system} robot{k}", cmd, run_dir / f"robot{k}.log", run_dir)


def wait_clients_ready(fleet: Fleet, run_dir: Path, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Every robot connected (stock: its server loaded the policy); fail if anything died.

    Says every 10 s how many are connected: a run cut from outside shows in its log where it was.
    """
    t0 = time.monotonic()
    deadline, next_report = t0 + timeout_s, t0 + 10.0
    while time.monotonic() < deadline:
        for p in fleet.servers + fleet.clients:
            if p.popen.poll() is not None:
                raise RunFailed(p.failed())
        ready = sum((run_dir / f"ready{k}").exists() for k in range(len(fleet.clients)))
        if ready == len(fleet.clients):
            return
        if time.monotonic() >= next_report:
            waited = time.monotonic() - t0
            print(f"    {waited:5.0f} s   {ready} of {len(fleet.clients)} robot(s) connected", flush=True)
            next_report += 10.0
        time.sleep(0.1)
    raise RunFailed(f"robots not connected within {timeout_s:.0f} s")


# ---- /proc measurements ------------------------------------------------------------------------


def rss_bytes(pid: int) -> int:
    """VmRSS of ``pid`` (0 once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def gpu_memory_used_bytes() -> int | None:
    """Memory in use on GPU 0 as ``nvidia-smi`` reports it (every process's; None without one).

    Read from outside the processes so the monitor opens no CUDA context of its own; the device
    machine runs nothing but this benchmark, so the figure is the servers' (and robots', which
    hold no CUDA memory) footprint: where it meets the GPU's size, stock runs out of copies.
    """
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits", "--id=0"],
            capture_output=True, text=True, check=True, timeout=5,
        )  # fmt: skip
        return int(out.stdout.split()[0]) * 2**20
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return None


class Monitor:
    """Samples the servers' summed RSS (peak), the GPU's memory in use (peak, on CUDA) and
    everyone's CPU seconds while a run lasts."""

    def __init__(self, fleet: Fleet, gpu: bool = False) -> None:
        self.fleet = fleet
        self.peak_rss = 0
        self.gpu = gpu
        self.peak_gpu: int | None = None
        self.client_cpu = {p.popen.pid: cpu_seconds(p.popen.pid) for p in fleet.clients}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            self.sample()

    def sample(self) -> None:
        self.peak_rss = max(self.peak_rss, sum(rss_bytes(p.popen.pid) for p in self.fleet.servers))
        if self.gpu and (used := gpu_memory_used_bytes()) is not None:
            self.peak_gpu = max(self.peak_gpu or 0, used)
        for p in self.fleet.clients:
            if p.popen.poll() is None:
                self.client_cpu[p.popen.pid] = max(self.client_cpu[p.popen.pid], cpu_seconds(p.popen.pid))

    def __enter__(self) -> Self:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def measure(fleet: Fleet, run_dir: Path, duration_s: float, label: str, gpu: bool = False) -> dict[str, float | None]:
    """Start the robots (the go file), follow the run with progress lines; CPU, RSS and GPU memory figures."""
    servers = [p.popen.pid for p in fleet.servers]
    with Monitor(fleet, gpu) as mon:
        client_cpu0 = dict(mon.client_cpu)
        server_cpu0 = sum(cpu_seconds(pid) for pid in servers)
        machine0, t0 = machine_cpu(), time.monotonic()
        (run_dir / "go").write_text("go\n")
        next_report = t0 + 10.0
        while any(p.popen.poll() is None for p in fleet.clients):
            for p in fleet.servers:
                if p.popen.poll() is not None:
                    raise RunFailed(p.failed())
            if time.monotonic() > t0 + duration_s + 120:
                raise RunFailed(f"{label}: robots still running {duration_s + 120:.0f} s after the start")
            if time.monotonic() >= next_report:
                print(
                    f"    {time.monotonic() - t0:5.0f} / {duration_s:.0f} s   servers RSS {gib(mon.peak_rss)} GiB"
                    + ("" if mon.peak_gpu is None else f", GPU memory {gib(mon.peak_gpu)} GiB"),
                    flush=True,
                )
                next_report += 10.0
            time.sleep(0.2)
        wall = min(time.monotonic() - t0, duration_s)  # the robots' window; servers idle after it
        server_cpu = sum(cpu_seconds(pid) for pid in servers) - server_cpu0
        machine1 = machine_cpu()
    for p in fleet.clients:
        if p.popen.returncode:
            raise RunFailed(p.failed())
    client_cpu = sum(mon.client_cpu[pid] - client_cpu0[pid] for pid in client_cpu0)
    return {
        "server_rss_peak_bytes": float(mon.peak_rss),
        "gpu_memory_peak_bytes": None if mon.peak_gpu is None else float(mon.peak_gpu),
        "server_cpu_pct": 100.0 * server_cpu / max(1e-9, wall),
        "robots_cpu_pct": 100.0 * client_cpu / max(1e-9, wall),
        "machine_busy_pct": 100.0 * (machine1[0] - machine0[0]) / max(1e-9, machine1[1] - machine0[1]),
    }


# ---- one run -----------------------------------------------------------------------------------


def start_fleet(opts: Options, variant: Variant, n: int, run_dir: Path) -> Fleet:
    """The servers of ``variant`` and its ``n`` robots, connected and waiting for the go.

    Prints when the servers are up and when the robots are connected (a stock server loads its
    policy only once its client connects, so for stock most of the time is the second part), and
    keeps the total in ``Fleet.ready_s``.
    """
    fleet = Fleet()
    t0 = time.monotonic()
    try:
        if variant.system == "ours":
            proc, address = start_ours_server(opts, variant.cpu_threads, run_dir)
            fleet.servers.append(proc)
            addresses = [address] * n
        else:
            started = start_stock_servers(opts, n, variant.system == "stock_nofilter", run_dir)
            fleet.servers.extend(p for p, _ in started)
            addresses = [a for _, a in started]
        print(f"    {len(fleet.servers)} server(s) up in {time.monotonic() - t0:.1f} s", flush=True)
        for k in range(n):
            fleet.clients.append(start_client(variant.system, robot_spec(opts, k, addresses[k], run_dir), k, run_dir))
        wait_clients_ready(fleet, run_dir)
    except BaseException:
        fleet.stop()
        raise
    fleet.ready_s = time.monotonic() - t0
    print(f"    {n} robot(s) connected: ready in {fleet.ready_s:.1f} s", flush=True)
    return fleet


def run_one(opts: Options, variant: Variant, n: int, work: Path) -> dict[str, Any]:
    """One system with N robots for ``duration_s``; its record (summary + per-robot stats)."""
    run_dir = work / f"{variant.label.replace(' ', '_').replace('(', '').replace(')', '')}-N{n}"
    run_dir.mkdir(parents=True, exist_ok=True)
    fleet = start_fleet(opts, variant, n, run_dir)
    try:
        usage = measure(fleet, run_dir, opts.duration_s, f"{variant.label} N={n}", gpu=opts.device.startswith("cuda"))
    finally:
        fleet.stop()
    robots = read_robot_stats(run_dir, n, f"{variant.label} N={n}")
    for r in robots:
        if r["chunks_received"] == 0:
            raise RunFailed(f"{variant.label} N={n}: {r['robot_id']} never received a chunk (logs in {run_dir})")
    summary = summarize(robots)
    for r in robots:  # the JSON keeps each robot's latency quantiles, not every chunk's
        lat = r.pop("latency_ms")
        r.update(latency_p50_ms=percentile(lat, 0.5), latency_p90_ms=percentile(lat, 0.9))
    return {"system": variant.system, "label": variant.label, "cpu_threads": variant.cpu_threads, "robots": n,
            **summary, **usage, "ready_s": fleet.ready_s, "per_robot": robots}  # fmt: skip


def read_robot_stats(run_dir: Path, n: int, label: str) -> list[dict[str, Any]]:
    """The stats JSON every robot process wrote at its end."""
    missing = [k for k in range(n) if not (run_dir / f"robot{k}.json").is_file()]
    if missing:
        raise RunFailed(f"{label}: robot(s) {missing} wrote no stats (logs in {run_dir})")
    return [json.loads((run_dir / f"robot{k}.json").read_text()) for k in range(n)]


def percentile(values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1) by nearest rank."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def summarize(robots: list[dict[str, Any]]) -> dict[str, float]:
    """Fleet figures from per-robot stats."""
    starvation = [r["starvation_pct"] for r in robots]
    latencies = [x for r in robots for x in r["latency_ms"]]
    return {
        "starvation_mean_pct": statistics.fmean(starvation),
        "starvation_max_pct": max(starvation),
        "starvation_with_startup_mean_pct": statistics.fmean(r["starvation_pct_all"] for r in robots),
        "ticks_per_s": statistics.fmean(r["ticks"] / r["wall_s"] for r in robots),
        "chunks_per_s": statistics.fmean(r["chunks_received"] / r["wall_s"] for r in robots),
        "latency_p50_ms": percentile(latencies, 0.5),
        "latency_p90_ms": percentile(latencies, 0.9),
        "first_chunk_s_max": max(r["first_chunk_s"] or 0.0 for r in robots),
        "foreign_chunks": sum(r["foreign_chunks"] for r in robots),
    }


# ---- the shared-server check --------------------------------------------------------------------


def shared_server_check(opts: Options, work: Path) -> dict[str, Any]:
    """Two stock clients on ONE stock server (filter off): chunks answering the other's observations."""
    run_dir = work / "stock-shared-server"
    run_dir.mkdir(parents=True, exist_ok=True)
    duration = min(opts.duration_s, 20.0)
    fleet = Fleet()
    try:
        (proc, address), = start_stock_servers(opts, 1, True, run_dir)  # fmt: skip
        fleet.servers.append(proc)
        for k in range(2):
            spec = {**robot_spec(opts, k, address, run_dir), "duration_s": duration}
            fleet.clients.append(start_client("stock", spec, k, run_dir))
            time.sleep(1.0)  # the second client's Ready comes after the first's
        wait_clients_ready(fleet, run_dir)
        measure(fleet, run_dir, duration, "stock shared server")
    finally:
        fleet.stop()
    robots = read_robot_stats(run_dir, 2, "stock shared server")
    return {
        "duration_s": duration,
        "per_robot": [
            {k: r[k] for k in ("robot_id", "chunks_received", "foreign_chunks", "starvation_pct")} for r in robots
        ],
        "chunks": sum(r["chunks_received"] for r in robots),
        "foreign_chunks": sum(r["foreign_chunks"] for r in robots),
    }


# ---- report ------------------------------------------------------------------------------------

HEADER = (
    "| system | N | starvation mean % | starvation max % | ticks/s | chunks/s per robot | latency p50 ms | "
    "latency p90 ms | server RSS GiB | GPU memory GiB | server CPU % | robots CPU % | machine busy % |"
)


def gib(value: float | None) -> str:
    """Bytes as GiB for the table; "–" where not measured (no GPU)."""
    return "–" if value is None else f"{value / 2**30:.2f}"


def table(runs: list[dict[str, Any]]) -> str:
    """The markdown table, one row per system × N."""
    lines = [HEADER, "|" + "---|" * HEADER.count(" | ") + "---|"]
    for r in runs:
        flag = " (busy)" if r["machine_busy_pct"] > BUSY_PCT else ""
        lines.append(
            f"| {r['label']} | {r['robots']} | {r['starvation_mean_pct']:.1f} | {r['starvation_max_pct']:.1f} | "
            f"{r['ticks_per_s']:.1f} | {r['chunks_per_s']:.2f} | {r['latency_p50_ms']:.0f} | {r['latency_p90_ms']:.0f} | "
            f"{gib(r['server_rss_peak_bytes'])} | {gib(r.get('gpu_memory_peak_bytes'))} | {r['server_cpu_pct']:.0f} | {r['robots_cpu_pct']:.0f} | "
            f"{r['machine_busy_pct']:.0f}{flag} |"
        )
    return "\n".join(lines)


def machine() -> dict[str, Any]:
    """Cores, CPU model, memory, GPU (if any), versions."""
    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict[str, Any] = {"cores": os.cpu_count(), "cpu_model": model, "python": platform.python_version()}
    try:
        info["memory_gib"] = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError):
        pass
    from importlib.metadata import version

    for dist in ("lerobot", "torch", "grpcio"):
        try:
            info[dist] = version(dist)
        except Exception:  # noqa: BLE001, S110 - a missing version is just not reported
            pass
    return info


def torch_default_threads() -> int:
    """torch's intra-op thread count in a fresh process (what a stock server runs with)."""
    out = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
        capture_output=True,
        text=True,
        check=False,
    )
    return int(out.stdout.strip() or 0)


def gpu_name(device: str) -> str | None:
    """The GPU's name when running on CUDA (imports torch only then)."""
    if not device.startswith("cuda"):
        return None
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None


NOTES = """\
- **Same policy, same robots.** Both sides load the same policy directory (sha256 of its weights
  above), the robots are the same `armory_sim` (same seeds, scene `{scene}`, 64×64 camera), one
  process per robot on both sides, fps {fps}, chunk {chunk}, a new chunk after {h_min} executed steps (ours:
  `--h_min={h_min} --h_max={chunk}`; stock: `chunk_size_threshold={threshold:g}`, it asks when ≤ {left} of {chunk} actions are
  left). Starvation = control ticks with no action to execute / ticks, per robot, counted from
  the robot's {settle} (the stock server's first forward pass is cold, ours is warmed by the
  start-up profiling); `starvation_with_startup_mean_pct` in the JSON counts every tick.
- **One stock server per robot.** A stock `policy_server` serves one client: a client's `Ready`
  resets it, and two clients on one server share its single observation queue, so each receives
  chunks computed from the other's observations (the shared-server check above counts them). N
  robots need N servers, each with its own Python + torch runtime and its own copy of the policy:
  server memory grows with N (server RSS column), and the N servers each run torch with
  {stock_threads} intra-op thread(s) on the same cores (torch's default unless
  `--stock_cpu_threads`), while ours is one process with one batched model.
- **The stock similarity filter** (`observations_similar`, lerobot's async helpers): the server
  skips an observation whose state is within L2 1.0 of the last one it served unless the client
  marked it `must_go` (its queue is empty). 1.0 suits joint angles in degrees; armory_sim's
  positions lie in [-1, 1], so nearly every observation is skipped, the client gets a new chunk
  only once its queue has run dry, and it starves for about one inference per chunk. `stock` is
  what a user gets out of the box; `stock_nofilter` (the filter patched to "never similar" in
  `benchmarks/_stock_async.py`; the "timestep already predicted" check stays) measures the stock
  serving path itself. Both are reported so neither reading is hidden. Without the filter the
  stock server computes more chunks than a robot consumes (a robot executes {chunks_per_s:.3g} chunks/s of {h_min}
  steps): while a chunk is in flight the client keeps sending an observation every tick, and the
  server turns the newest of them into one more chunk (chunks/s and server CPU columns).
- **Stock timing.** The stock server holds every answer until `inference_latency` (default 1/fps
  = 33 ms) has passed since its `GetActions` call began waiting, so a chunk takes at least that
  unless the call had already waited. The stock control loop sleeps `1/fps − elapsed` with no
  catching up, so it ticks a little below 30 Hz (ticks/s column); a slower robot consumes its
  chunk more slowly, which lowers its starvation for the same serving. Ours ticks on a fixed
  schedule. Once its queue holds ≤ {left} actions the stock client sends an observation (pickled, with
  the full image) every tick until a chunk arrives; the server keeps only the newest. Overlapping
  actions are merged with `weighted_average` (0.3 old + 0.7 new); ours switches to the newest chunk.
  The stock server logs several INFO lines per chunk (to stdout and `./logs/`), part of its CPU.
- **Chunk latency** is observation capture → chunk usable on the robot, on the robot's clock:
  stock from the `TimedObservation` timestamp (`time.time()` right after `get_observation`) to
  after unpickling the chunk; ours from the capture time (just before `get_observation`) to the
  chunk's arrival. Server CPU is % of one core over the robots' window, from `/proc/PID/stat`
  (summed over the stock servers); server RSS is the peak of the summed `VmRSS`.
- **Noise.** "machine busy %" is the whole machine over the run (other processes included); a row
  marked *(busy)* ran on a saturated machine and measures the machine as much as the system.
"""


def markdown(report: dict[str, Any]) -> str:
    """The results page."""
    m = report["machine"]
    lines = [
        "# Our server vs LeRobot's async inference (policy_server + robot_client)",
        "",
        f"Machine: {m['cores']} cores, {m['cpu_model']}, {m.get('memory_gib', '?')} GiB"
        + (f", GPU {report['gpu']}" if report.get("gpu") else "")
        + f"; lerobot {m.get('lerobot', '?')}, torch {m.get('torch', '?')}, Python {m['python']}.",
        (
            f"Device: `{report['device']}`. Ours: `--scheduler.type={report['ours_scheduler']}`, "
            f"`--max_batch_size={report['max_batch_size']}`. {report['duration_s']:g} s per run. "
            f"Policy: `{report['policy']}` ({report.get('policy_type', '?')}), chunk {report.get('chunk', CHUNK)} (weights sha256 `{report['policy_sha256'][:16]}…`)."
        ),
        "",
        "```",
        report["command"],
        "```",
        "",
        table(report["runs"]),
        "",
    ]
    shared = report.get("stock_shared_server")
    if shared:
        each = ", ".join(f"{r['robot_id']}: {r['foreign_chunks']}/{r['chunks_received']}" for r in shared["per_robot"])
        lines += [
            (
                f"**Two stock clients on one stock server** ({shared['duration_s']:g} s, filter off): "
                f"{shared['foreign_chunks']} of {shared['chunks']} chunks answered the *other* client's observation "
                f"({each})."
            ),
            "",
        ]
    lines += ["## Notes", "", notes(report)]
    return "\n".join(lines)


def notes(report: dict[str, Any]) -> str:
    """``NOTES`` with this report's timing (a report without ``chunk`` ran the default)."""
    chunk, settle = int(report.get("chunk", CHUNK)), int(report.get("settle_chunks", 1))
    h_min = h_min_of(chunk)
    return NOTES.format(
        scene=report["scene"], stock_threads=report["stock_threads"], fps=FPS, chunk=chunk, h_min=h_min,
        left=chunk - h_min, threshold=THRESHOLD, chunks_per_s=FPS / h_min,
        settle="first chunk" if settle == 1 else f"chunk number {settle} on (`--settle_chunks`)",
    )  # fmt: skip


# ---- main --------------------------------------------------------------------------------------


def int_list(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def parse_args(argv: list[str] | None = None) -> Options:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", default="1,2,4,8", help="fleet sizes N, comma-separated")
    ap.add_argument("--duration_s", type=float, default=60.0, help="seconds per run")
    ap.add_argument("--systems", default=",".join(SYSTEMS), help=f"comma-separated: {', '.join(SYSTEMS)}")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (both sides)")
    ap.add_argument(
        "--ours_cpu_threads",
        default="",
        help="--policy.cpu_threads for ours; a list (1,2) runs each; empty: the server's default",
    )
    ap.add_argument(
        "--ours_scheduler", default="lookahead", help="--scheduler.type for ours (lookahead is the server's default)"
    )
    ap.add_argument("--max_batch_size", type=int, default=3, help="ours: batch cap (the server's default is 3)")
    ap.add_argument("--ours_server_args", default="", help="more lerobot-armory-server options for ours (e.g. --latency_learning=false)")
    ap.add_argument(
        "--stock_cpu_threads",
        type=int,
        default=0,
        help="torch threads per stock server (0: torch's default, as stock runs)",
    )
    ap.add_argument("--scene", default="dynamic", choices=("static", "dynamic"), help="armory_sim scene of every robot")
    ap.add_argument(
        "--chunk",
        type=int,
        default=CHUNK,
        help="the robots' chunk H: both sides execute at most H actions of a chunk and ask for the next after H/2; "
        "the policy's chunk_size must be >= H",
    )
    ap.add_argument(
        "--settle_chunks",
        type=int,
        default=1,
        help="starvation is counted from each robot's K-th chunk on, on both sides (1: from the first; more keeps a "
        "system's cold first passes, e.g. stock's lazy CUDA set-up, out of the figure; every tick: starvation_with_startup)",
    )
    ap.add_argument("--policy", default="", help="policy directory (default: the demo ACT built with --chunk, in out/)")
    ap.add_argument("--out", help="write <device>.md and <device>.json here (e.g. docs/results/vs_lerobot_async)")
    ap.add_argument("--work_dir", help="where logs and per-robot stats go (default: a temporary directory)")
    ap.add_argument(
        "--stock_shared_server",
        action="store_true",
        help="also show two stock clients on one stock server mixing chunks",
    )
    a = ap.parse_args(argv)
    systems = [s.strip() for s in a.systems.split(",") if s.strip()]
    unknown = [s for s in systems if s not in SYSTEMS]
    robots = int_list(a.robots)
    if unknown or not systems:
        ap.error(f"--systems: unknown {unknown}; known: {', '.join(SYSTEMS)}")
    if not robots or min(robots) < 1 or a.duration_s <= 0:
        ap.error("--robots must be positive integers and --duration_s > 0")
    if a.settle_chunks < 1:
        ap.error(f"--settle_chunks must be >= 1, got {a.settle_chunks}")
    if a.chunk < 2:
        ap.error(f"--chunk must be >= 2 (a robot asks for the next chunk after half of it), got {a.chunk}")
    threads: list[int | None] = list(int_list(a.ours_cpu_threads)) or [None]
    if any(t is not None and t < 1 for t in threads):
        ap.error("--ours_cpu_threads: must be >= 1")
    return Options(
        robots, a.duration_s, systems, a.device, threads, a.ours_scheduler, a.max_batch_size, a.stock_cpu_threads,
        a.scene, a.policy, a.out, a.work_dir, a.stock_shared_server, a.ours_server_args, a.chunk, a.settle_chunks,
    )  # fmt: skip


def ensure_policy(opts: Options) -> str:
    """The policy directory (absolute): the given one, or the demo ACT with ``--chunk``, built once
    per chunk (the directory is named after it)."""
    if opts.policy:
        path = Path(opts.policy).resolve()
    else:
        path = (Path("out") / f"vs-lerobot-act-H{opts.chunk}").resolve()
        if not (path / "config.json").is_file():
            maker = Path(sys.executable).parent / "lerobot-armory-make-demo-policy"
            subprocess.run(
                [str(maker), f"--output={path}", f"--chunk_size={opts.chunk}", f"--image_size={IMAGE_SIZE}"], check=True
            )
    if not (path / "config.json").is_file():
        raise RunFailed(f"{path}: not a policy directory (no config.json)")
    return str(path)


def check_policy_chunk(policy: str, chunk: int) -> None:
    """Refuse a policy whose chunks are shorter than ``--chunk``.

    Both sides would run another timing than the one reported: stock cuts the model's chunk to
    ``actions_per_chunk`` and asks relative to the longest chunk it received, ours executes at most
    ``h_max`` of the model's chunk. A π0/π0.5 directory also names ``n_action_steps`` (what its
    ``select_action`` executes); neither side reads it here, but a directory built for a shorter
    chunk would show it, so it is held to the same bound.
    """
    config = json.loads((Path(policy) / "config.json").read_text())
    keys = ["chunk_size"] + (["n_action_steps"] if config.get("type") in ("pi05", "pi0") else [])
    if "chunk_size" not in config:  # e.g. diffusion (horizon): not refused, but said
        print(f"warning: {policy}/config.json names no chunk_size: --chunk={chunk} not checked against it", flush=True)
    short = [f"{key}={config[key]}" for key in keys if key in config and int(config[key]) < chunk]
    if short:
        raise RunFailed(
            f"--chunk={chunk} needs a policy predicting at least {chunk} actions per chunk, but "
            f"{policy}/config.json has {', '.join(short)}: build the policy with --chunk_size={chunk} (or more), "
            "or pass a smaller --chunk"
        )


def weights_sha256(policy: str) -> str:
    """sha256 of the policy's weight file (the very file both systems load)."""
    return hashlib.sha256((Path(policy) / "model.safetensors").read_bytes()).hexdigest()


def variants(opts: Options) -> list[Variant]:
    """Systems as run, ours once per thread count."""
    out: list[Variant] = []
    for system in opts.systems:
        out += [Variant("ours", t) for t in opts.ours_cpu_threads] if system == "ours" else [Variant(system)]
    return out


def report_header(opts: Options, command: str) -> dict[str, Any]:
    """What ``write`` stores besides the runs: the command, the machine, the policy (its weights'
    sha256: a read of the whole file, so made once)."""
    return {
        "command": command, "machine": machine(), "gpu": gpu_name(opts.device), "device": opts.device,
        "duration_s": opts.duration_s, "ours_scheduler": opts.ours_scheduler, "ours_server_args": opts.ours_server_args, "max_batch_size": opts.max_batch_size,
        "scene": opts.scene, "stock_threads": opts.stock_cpu_threads or torch_default_threads(), "policy": opts.policy,
        "policy_type": policy_type(opts.policy), "policy_sha256": weights_sha256(opts.policy),
        "chunk": opts.chunk, "fps": FPS, "h_min": h_min_of(opts.chunk), "chunk_size_threshold": THRESHOLD,
        "settle_chunks": opts.settle_chunks,
    }  # fmt: skip


def write(opts: Options, report: dict[str, Any]) -> None:
    """``<device>.json`` and ``<device>.md`` under ``--out``."""
    if not opts.out:
        return
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "cpu" if opts.device == "cpu" else "cuda"
    (out / f"{name}.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / f"{name}.md").write_text(markdown(report))
    print(f"wrote {out / name}.md and .json")


def main(argv: list[str] | None = None) -> None:
    opts = parse_args(argv)
    command = "python benchmarks/vs_lerobot_async.py " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)
    )
    try:
        opts.policy = ensure_policy(opts)
        check_policy_chunk(opts.policy, opts.chunk)
        work = Path(opts.work_dir or tempfile.mkdtemp(prefix="vs-lerobot-async-")).resolve()
        todo = [(v, n) for n in opts.robots for v in variants(opts)]  # systems interleaved per N: drift hits all alike
        print(
            f"{len(todo)} run(s) of {opts.duration_s:g} s on {opts.device}; policy {opts.policy}; logs in {work}",
            flush=True,
        )
        print(f"chunk {opts.chunk}, a new one after {h_min_of(opts.chunk)} executed steps, at {FPS} fps", flush=True)
        header = report_header(opts, command)
        runs = []
        for k, (variant, n) in enumerate(todo):
            print(f"[{k + 1}/{len(todo)}] {variant.label} N={n} ...", flush=True)
            record = run_one(opts, variant, n, work)
            print(f"    starvation mean {record['starvation_mean_pct']:.1f} % max {record['starvation_max_pct']:.1f} %, "
                  f"{record['chunks_per_s']:.2f} chunks/s per robot, latency p50 {record['latency_p50_ms']:.0f} ms, "
                  f"servers {gib(record['server_rss_peak_bytes'])} GiB RSS, GPU memory {gib(record['gpu_memory_peak_bytes'])} GiB, "
                  f"{record['server_cpu_pct']:.0f} % CPU, ready in {record['ready_s']:.0f} s", flush=True)  # fmt: skip
            runs.append(record)
            write(opts, {**header, "runs": runs, "stock_shared_server": None})  # kept as each run ends: a call cut short loses only the run under way
            time.sleep(1.0)
        shared = None
        if opts.stock_shared_server:
            print("[check] two stock clients on one stock server ...", flush=True)
            shared = shared_server_check(opts, work)
            print(
                f"    {shared['foreign_chunks']} of {shared['chunks']} chunks answered the other client's observation",
                flush=True,
            )
    except RunFailed as exc:
        print(f"vs_lerobot_async: error: {exc}", file=sys.stderr)
        sys.exit(1)
    report = {**header, "runs": runs, "stock_shared_server": shared}
    print()
    print(table(runs))
    if shared:
        print(
            f"\ntwo stock clients on one stock server: {shared['foreign_chunks']} of {shared['chunks']} chunks were the other's"
        )
    write(opts, report)


if __name__ == "__main__":
    main()

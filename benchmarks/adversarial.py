"""One robot cannot hurt the fleet: the real server attacked by a hostile or broken robot.

Each run starts ``lerobot-armory-server`` (the analytic planner policy, H=10, 64 px camera,
``--engine.emulate_profile=l40s-pi05``, ``--max_batch_size=3``; started with the usual soft
limit of 1024 open files, as systemd and most shells give it), one process of four honest
``armory_sim`` robots (20 fps, h_min 5, h_max 10, weight 1, emulated network 3.75 ms median with
the libero preset's jitter; ``python tests/support/adversaries.py honest SPEC.json``) and, in this
process, on its own thread, one attacker from ``tests/support/adversaries.py`` speaking the raw
protocol. The honest robots tick for ``warmup_s + duration_s``; the attacker starts after the
warm-up (or, for the attacks on joining — slot_squat, identity, idle_sockets, openpi_idle — before the honest
robots start). The same honest fleet without an attacker, once per scheduler, is the baseline;
it serves one more honest robot in the attacker's place (for openpi_never_reads: as many openpi
clients as the attacker opens connections, that read their replies and ask again at once).

A row passes when

- the server is up at the end of the attack (process alive, gRPC health SERVING);
- the honest robots' mean starvation over the attack window is at most ``tolerance_pp`` (2)
  percentage points above the baseline's over the same window (for slot_squat and idle_sockets:
  from each robot's first chunk on, plus every robot's first chunk within ``join_limit_s``; for
  clock_step: the stepped robot from 1 s after its step, and the others from the step);
- the server's RSS grew less than ``rss_limit_mib`` (200 MiB) over the attack, at its end and at
  its peak (sampled every 0.25 s while the attack runs);
- the attacker saw no violation (an impersonation accepted, an absurd registration granted);
- every honest robot ran (none refused for good);
- the server still shuts down gracefully on SIGTERM (within 15 s) after the attack.

Prints one line per run and a table; writes ``README.md`` and ``results.json`` to
``--output_dir``; exits 1 if any row fails.

    .venv/bin/python benchmarks/adversarial.py                       # everything, ~15 min
    .venv/bin/python benchmarks/adversarial.py --quick               # one scheduler, short runs
    .venv/bin/python benchmarks/adversarial.py --scenarios=clock_nan,huge_report --schedulers=edf
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
from tests.support import adversaries as adv  # noqa: E402 - the attackers are the tests' doubles

from lerobot_armory.bench.live import machine_cpu
from lerobot_armory.sim.presets import get_preset

ALL_SCENARIOS = (
    "clock_nan", "capture_absurd", "report_absurd", "fps_absurd", "priority_flood", "clock_ahead", "huge_report",
    "never_reads", "slot_squat", "identity", "clock_step", "idle_sockets", "garbage", "openpi_idle", "openpi_garbage",
    "share_liar", "openpi_never_reads",
)  # fmt: skip
# Honest controls, run only when named: share_lean is share_liar's client without the lie (it
# claims only what it executed), to tell what the lie buys from what a lean, fast client gets.
CONTROLS = ("share_lean",)
SHARE_SCENARIOS = ("share_liar", "share_lean")
# Attacks on something every scheduler shares (memory, sockets, slots, credentials, parsing) run
# once, under the first of these that is selected; the others run under every scheduler.
ONCE = ("never_reads", "slot_squat", "identity", "idle_sockets", "garbage", "openpi_idle", "openpi_garbage", "openpi_never_reads")
SINGLE_PREFERENCE = ("lookahead", "edf", "rr", "rollout")
SCHEDULERS = ("rr", "edf", "lookahead", "rollout")
# share_liar: the liar's chunks/s may be at most this multiple of its lean honest twin's (its own
# client and registration, honest, in the same run), under every scheduler; rollout is always added.
SHARE_LIMIT = 1.15
SHARE_REGISTRATION = (("h_min", 0),)
# clock_ahead registers h_min 1 (served as often as it likes): its stand-in and twin register so
# too, so that the row measures the clock lie, not the registration (the grant rules's h_min
# floor governs that; docs/security.md gives what a greedy registration costs the others).
CLOCK_AHEAD_REGISTRATION = (("h_min", 1),)
# openpi_never_reads: its connections, and the baseline's stand-in: as many openpi clients that read.
OPENPI_NEVER_READS_CONNECTIONS = 3
JOIN = {"slot_squat": 10.0, "idle_sockets": 5.0, "openpi_idle": 10.0}  # scenario -> join limit (s)
LEAD_S = 1.5  # attacks on joining start this long before the honest robots
STEP_SETTLE_S = 1.0  # clock_step: the stepped robot is judged from this long after its step
HONEST = 4  # honest robots per run (--honest); main() sets it before planning, every function reads it
CAP = 3


@dataclass
class Config:
    scenarios: str = ",".join(ALL_SCENARIOS)
    schedulers: str = "rr,edf,lookahead"
    duration_s: float = 10.0
    warmup_s: float = 2.0
    output_dir: str = "docs/results/adversarial"
    quick: bool = False
    image_size: int = 64
    tolerance_pp: float = 2.0
    rss_limit_mib: float = 200.0
    never_reads_mib: float = 300.0
    seed: int = 0
    policy_path: str | None = None
    work_dir: str | None = None
    before: str | None = None  # results.json of an earlier run, shown beside each row in README.md
    server_nofile: int = 1024  # soft RLIMIT_NOFILE the server starts with (0: this process's)
    before_label: str | None = None  # what --before was run on, for README.md
    # The baseline serves one more honest robot in the attacker's place (not measured): an attacker
    # is compared with an honest robot that asks for the same service, not with no robot at all,
    # which in a saturated fleet (--honest 8) would charge it with the load of any robot.
    standin: bool = True


@dataclass
class RunSpec:
    """One live run: a scenario (or the baseline) under one scheduler and batch cap."""

    scenario: str  # "baseline" or a scenario name
    scheduler: str
    cap: int = CAP
    variant: str = ""  # "+1h" / "-1h" for clock_step
    attack: str | None = None
    attack_kwargs: dict[str, Any] = field(default_factory=dict)
    server_args: list[str] = field(default_factory=list)
    lead: bool = False
    step_s: float = 0.0
    tokens: dict[str, str] = field(default_factory=dict)  # honest robot id -> token
    duration_s: float | None = None  # attack window if not the config's (never_reads: until all is sent)
    standin: tuple[tuple[str, Any], ...] = ()  # the baseline stand-in's registration, where it is not an honest robot's
    # The baseline's stand-in where it is not an armory_sim robot: one of adversaries.STANDINS, run
    # in the attacker's place with ``standin_kwargs`` (and the attacked run's server options).
    standin_attack: str = ""
    standin_kwargs: tuple[tuple[str, Any], ...] = ()
    metrics_port: int = 0  # scrape the server's chunks per robot at the end of the window (0: no)

    @property
    def baseline_key(self) -> tuple[str, int, tuple[tuple[str, Any], ...], str, tuple[tuple[str, Any], ...]]:
        return (self.scheduler, self.cap, self.standin, self.standin_attack, self.standin_kwargs)

    @property
    def sched_label(self) -> str:
        label = self.scheduler if self.cap == CAP else f"{self.scheduler} b={self.cap}"
        if self.scenario != "baseline":
            return label
        label += "".join(f", stand-in {k} {v}" for k, v in self.standin)
        if self.standin_attack:
            label += f", stand-in {self.standin_attack}" + "".join(f" {k}={v}" for k, v in self.standin_kwargs)
        return label

    @property
    def label(self) -> str:
        name = f"{self.scenario}({self.variant})" if self.variant else self.scenario
        return f"{name} / {self.sched_label}"

    @property
    def slug(self) -> str:
        return re.sub(r"[^A-Za-z0-9]+", "-", self.label).strip("-")


# ---- the server process --------------------------------------------------------------------------

LOG_PREFIX = re.compile(r"^\S+ \S+ (?:DEBUG|INFO|WARNING|ERROR|CRITICAL) \S+: ")
EXC_LINE = re.compile(r"^([A-Za-z_][\w.]*(?:Error|Exception|Exit|Interrupt)): ?(.*)$")


class ServerProcess:
    """``lerobot-armory-server`` as a subprocess whose output is drained (a full pipe would block
    its logging, and so the server) and kept: the last lines, exceptions and crash lines."""

    def __init__(self, args: list[str], nofile: int = 0) -> None:
        command = [sys.executable, "-m", "lerobot_armory.entrypoints.server", *args]
        if nofile:  # the soft fd limit most services start with (systemd, shells): 1024; exec keeps the pid
            soft = min(nofile, resource.getrlimit(resource.RLIMIT_NOFILE)[1])
            command = ["/bin/sh", "-c", f'ulimit -S -n {soft} && exec "$0" "$@"', *command]
        self.proc = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}
        )
        self.lines: deque[str] = deque(maxlen=300)
        self.banner: list[str] = []
        self.exceptions: Counter = Counter()
        self.crash: list[str] = []
        self.address = ""
        self._banner_done = False
        deadline = time.monotonic() + 180
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                break
            self.banner.append(line.rstrip("\n"))
            if "listening on" in line:
                self.address = line.split("listening on")[1].strip()
                break
        if not self.address:
            self.proc.kill()
            raise RuntimeError("the server did not start:\n" + "\n".join(self.banner[-20:]))
        # The rest of the banner (features, profile) arrives right after.
        self._drain = threading.Thread(target=self._read, daemon=True)
        self._drain.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        after_crash = False
        for raw in self.proc.stdout:
            line = raw.rstrip("\n")
            self.lines.append(line)
            if not self._banner_done:  # the start-up summary printed right after "listening on"
                self.banner.append(line)
                self._banner_done = "d_infer learning" in line or len(self.banner) > 80
            m = EXC_LINE.match(line.strip())
            if m:
                self.exceptions[f"{m.group(1)}: {m.group(2)[:160]}"] += 1
                if after_crash:
                    self.crash.append(f"{m.group(1)}: {m.group(2)[:200]}")
                    after_crash = False
            if "crashed" in line or "serving loop died" in line or "stopping:" in line:
                self.crash.append(LOG_PREFIX.sub("", line.strip())[:240])
                after_crash = "crashed" in line

    def features(self, timeout: float = 10.0) -> dict[str, tuple[str, tuple[int, ...]]]:
        """The observation features the server expects, from its start-up banner."""
        deadline = time.monotonic() + timeout
        pattern = re.compile(r"^\s+(observation\.[^:]+): (\w+)\[([\d, ]*)\]$")
        while time.monotonic() < deadline:
            found = {}
            for line in list(self.banner):
                m = pattern.match(line)
                if m:
                    found[m.group(1)] = (m.group(2), tuple(int(d) for d in m.group(3).split(",") if d.strip()))
            if found and any("actions:" in line for line in self.banner):
                return found
            time.sleep(0.05)
        raise RuntimeError("no feature list in the server's banner:\n" + "\n".join(self.banner))

    def rss_mib(self) -> float | None:
        try:
            for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
        except OSError:
            return None
        return None

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def healthy(self, timeout: float = 5.0) -> bool:
        import grpc
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        channel = grpc.insecure_channel(self.address)
        try:
            answer = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""), timeout=timeout)
            return answer.status == health_pb2.HealthCheckResponse.SERVING
        except grpc.RpcError:
            return False
        finally:
            channel.close()

    def stop(self, timeout: float = 15.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout`` s (``stop_hung`` says so; ``shutdown_s`` how long)."""
        self.stop_hung, self.shutdown_s = False, 0.0
        if self.proc.poll() is None:
            t0 = time.monotonic()
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.stop_hung = True
                self.proc.kill()
                self.proc.wait()
            self.shutdown_s = time.monotonic() - t0
        self._drain.join(timeout=5)
        return self.proc.returncode


# ---- one run -------------------------------------------------------------------------------------


def ensure_policy(cfg: Config) -> str:
    """The planner policy directory (built if missing), as the live bench builds it."""
    if cfg.policy_path:
        return str(Path(cfg.policy_path).resolve())
    path = Path("out") / f"planner-H10-S{cfg.image_size}"
    if not (path / "config.json").is_file():
        from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

        make_demo_policy(DemoPolicyConfig(output=str(path), kind="planner", chunk_size=10, image_size=cfg.image_size))
    return str(path.resolve())


def honest_specs(spec: RunSpec, cfg: Config) -> list[dict[str, Any]]:
    robots = []
    for k in range(HONEST):
        fast = k < HONEST // 2
        r = {
            "robot_id": f"honest{k}", "tier": "fast" if fast else "slow", "scene": "dynamic" if fast else "static",
            "fps": 20.0, "h_min": 5, "h_max": 10, "weight": 1.0, "seed": 100 + k,
        }  # fmt: skip
        if spec.tokens:
            r["token"] = spec.tokens[r["robot_id"]]
        if spec.step_s and k == 0:
            r["clock_step_s"] = spec.step_s
            r["clock_step_at_s"] = step_at(cfg)
        robots.append(r)
    if spec.standin:  # an honest twin of the attacker's registration, in the attacked run and its baseline
        robots.append({
            "robot_id": "twin", "tier": "slow", "scene": "static", "fps": 20.0, "h_min": 5, "h_max": 10, "weight": 1.0,
            "seed": 98, **dict(spec.standin),
        })  # fmt: skip
    if spec.scenario == "baseline" and cfg.standin and not spec.standin_attack:
        robots.append({
            "robot_id": "standin", "tier": "slow", "scene": "static", "fps": 20.0, "h_min": 5, "h_max": 10, "weight": 1.0,
            "seed": 99, **({"token": spec.tokens["honest0"]} if spec.tokens else {}), **dict(spec.standin),
        })  # fmt: skip
    return robots


def step_at(cfg: Config) -> float:
    """When clock_step steps the robot's clock (seconds after the honest robots start)."""
    return cfg.warmup_s + cfg.duration_s / 2


def run_once(spec: RunSpec, cfg: Config, policy: str, work: Path) -> dict[str, Any]:
    """Server + honest robots (+ attacker); returns the raw record of the run."""
    run_dir = work / spec.slug
    stats_dir = run_dir / "stats"
    stats_dir.mkdir(parents=True, exist_ok=True)
    preset = get_preset("libero")
    ready, go = run_dir / "ready", run_dir / "go"
    for f in (ready, go):
        f.unlink(missing_ok=True)
    honest_s = cfg.warmup_s + (spec.duration_s or cfg.duration_s)
    group_spec = {
        "duration_s": honest_s, "stats_dir": str(stats_dir), "image_size": cfg.image_size,
        "net_median_ms": preset.net_median_ms, "net_sigma": preset.net_sigma,
        "ready_file": str(ready), "go_file": str(go), "robots": honest_specs(spec, cfg),
    }  # fmt: skip
    (run_dir / "group.json").write_text(json.dumps(group_spec, indent=1))
    group = subprocess.Popen([sys.executable, str(ROOT / "tests" / "support" / "adversaries.py"), "honest", str(run_dir / "group.json")])
    args = [
        f"--policy.path={policy}", "--policy.device=cpu", "--port=0", f"--scheduler.type={spec.scheduler}",
        f"--max_batch_size={spec.cap}", "--engine.emulate_profile=l40s-pi05", "--status_interval_s=0", "--log_level=warning",
        *spec.server_args,
    ]  # fmt: skip
    server = None
    report = adv.AttackReport(spec.scenario)
    stop = threading.Event()
    attacker: threading.Thread | None = None
    samples: list[tuple[float, float]] = []
    sampling = threading.Event()
    record: dict[str, Any] = {"label": spec.label, "scenario": spec.scenario, "variant": spec.variant, "scheduler": spec.sched_label}
    try:
        server = ServerProcess(args, cfg.server_nofile)
        features = server.features()
        deadline = time.monotonic() + 180
        while not ready.exists():
            if group.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the honest robot group did not start (exit code {group.returncode})")
            time.sleep(0.02)

        def sample() -> None:
            while not sampling.is_set():
                rss = server.rss_mib()
                if rss is not None:
                    samples.append((time.monotonic(), rss))
                sampling.wait(0.25)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()

        def attack() -> None:
            assert spec.attack is not None
            try:
                run = adv.SCENARIOS.get(spec.attack) or adv.STANDINS[spec.attack]
                run(server.address, stop, features, report, **spec.attack_kwargs)
            except Exception as exc:  # noqa: BLE001 - the attacker's own failure is reported, not fatal
                report.event(f"attacker failed: {type(exc).__name__}: {exc}")
                report.extra["attacker error"] = f"{type(exc).__name__}: {exc}"

        if spec.attack is not None:
            attacker = threading.Thread(target=attack, name=f"attacker-{spec.attack}", daemon=True)
        busy0 = machine_cpu()
        if spec.lead and attacker is not None:
            attacker.start()
            time.sleep(LEAD_S)
            rss0 = server.rss_mib()
            go.write_text(server.address)
        else:
            go.write_text(server.address)
            time.sleep(cfg.warmup_s)
            rss0 = server.rss_mib()
            if attacker is not None:
                attacker.start()
        t_attack = time.monotonic()
        try:
            code = group.wait(timeout=honest_s + 120)
        except subprocess.TimeoutExpired:
            group.kill()
            code = group.wait()
        rss_end = server.rss_mib()
        if spec.metrics_port:
            record["chunks_served"] = chunks_served(spec.metrics_port)
        busy1 = machine_cpu()
        alive = server.alive
        healthy = alive and server.healthy()
        stop.set()
        if attacker is not None:
            attacker.join(timeout=20)
            if attacker.is_alive():
                report.event("attacker did not stop within 20 s")
        sampling.set()
        peak = max((r for t, r in samples if t >= t_attack), default=rss_end or 0.0)
        exit_code = server.stop()
        record.update(
            {
                "shutdown_s": server.shutdown_s,
                "shutdown_hung": server.stop_hung,
                "server_alive": alive,
                "server_healthy": healthy,
                "server_exit_code": exit_code if not alive else None,
                "server_crash": list(server.crash)[:6],
                "server_exceptions": dict(server.exceptions.most_common(8)),
                "server_log_tail": list(server.lines)[-15:],
                "rss_start_mib": rss0,
                "rss_end_mib": rss_end,
                "rss_peak_mib": peak,
                "rss_growth_mib": (rss_end - rss0) if (rss_end is not None and rss0 is not None) else None,
                "rss_peak_growth_mib": (peak - rss0) if rss0 is not None else None,
                "machine_busy_pct": 100.0 * (busy1[0] - busy0[0]) / max(1e-9, busy1[1] - busy0[1]),
                "group_exit_code": code,
                "attack": report.to_json(),
                "attack_summary": report.summary(),
            }
        )
    finally:
        stop.set()
        sampling.set()
        if group.poll() is None:
            group.kill()
            group.wait()
        if server is not None and server.alive:
            server.stop()
    record["robots"] = [json.loads(p.read_text()) for p in sorted(stats_dir.glob("*.json"))]
    return record


def chunks_served(port: int) -> dict[str, float] | str:
    """``armory_robot_chunks_served_total`` per robot id, from the server's metrics endpoint."""
    import urllib.request

    from prometheus_client.parser import text_string_to_metric_families

    try:
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    except OSError as exc:
        return f"metrics not read: {exc}"
    return {
        sample.labels["robot_id"]: sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
        if sample.name == "armory_robot_chunks_served_total"
    }


# ---- judging -------------------------------------------------------------------------------------


def timeline(stats: dict[str, Any]) -> adv.Timeline:
    return adv.Timeline(list(stats["tick_times"]), [int(c) for c in stats["executed"]], stats.get("first_chunk_s"))


def mean(xs: list[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return float(np.mean(vals)) if vals else None


def windows(spec: RunSpec, cfg: Config) -> dict[str, Any]:
    """How the run is judged: which robots over which window (per robot: start time or 'first chunk')."""
    if spec.scenario == "clock_step":
        return {"stepped": ("honest0", step_at(cfg) + STEP_SETTLE_S), "others_from": step_at(cfg)}
    if spec.scenario in JOIN:
        return {"from": "first_chunk"}
    return {"from": 0.0 if spec.lead else cfg.warmup_s}


def honest_starvation(robots: list[dict[str, Any]], win: dict[str, Any], only: str | None = None, exclude: str | None = None) -> float | None:
    """Mean starvation (%) of the honest robots in the window; a robot with no stats counts 100."""
    values: list[float | None] = []
    ids = [f"honest{k}" for k in range(HONEST)]
    by_id = {r["robot_id"]: r for r in robots}
    for rid in ids:
        if (only and rid != only) or (exclude and rid == exclude):
            continue
        r = by_id.get(rid)
        if r is None:
            values.append(100.0)
            continue
        tl = timeline(r)
        if win.get("from") == "first_chunk":
            values.append(tl.starvation_pct(tl.first_chunk_s) if tl.first_chunk_s is not None else 100.0)
        else:
            values.append(tl.starvation_pct(win["from"]))
    return mean(values)


def judge(spec: RunSpec, record: dict[str, Any], baseline: dict[str, Any] | None, cfg: Config) -> dict[str, Any]:
    """Pass/fail of one attacked run against its baseline, with the reasons."""
    win = windows(spec, cfg)
    failures: list[str] = []
    notes: list[str] = []
    row: dict[str, Any] = {"label": record["label"], "scenario": spec.scenario, "variant": spec.variant, "scheduler": spec.sched_label}
    up = bool(record.get("server_alive") and record.get("server_healthy"))
    row["server_up"] = up
    if not up:
        if record.get("server_alive"):
            why = ["process alive but not answering its health check", *record.get("server_crash", [])]
        else:
            why = record.get("server_crash") or [f"process exited with code {record.get('server_exit_code')}"]
        failures.append("server down: " + " | ".join(why[:3]))
    elif record.get("server_crash"):
        failures.append("server: " + " | ".join(record["server_crash"][:2]))
    if record.get("shutdown_hung"):
        failures.append(f"graceful shutdown hung after the attack (SIGTERM, killed after {record.get('shutdown_s', 0):.0f} s)")
    robots, base_robots = record["robots"], (baseline or {}).get("robots", [])
    if spec.scenario == "clock_step":
        rid, start = win["stepped"]
        stepped = honest_starvation(robots, {"from": start}, only=rid)
        stepped_base = honest_starvation(base_robots, {"from": start}, only=rid) if baseline else None
        half = honest_starvation(robots, {"from": step_at(cfg)}, only=rid)
        row["stepped_pct"], row["stepped_base_pct"], row["stepped_half_pct"] = stepped, stepped_base, half
        if stepped is not None and stepped_base is not None:
            row["stepped_delta_pp"] = stepped - stepped_base
            if stepped - stepped_base > cfg.tolerance_pp:
                failures.append(f"stepped robot starves {stepped:.1f}% from {STEP_SETTLE_S:g} s after its step (baseline {stepped_base:.1f}%)")
        notes.append(f"stepped robot: {half:.1f}% over the whole second half" if half is not None else "stepped robot: no ticks")
        attack_pct = honest_starvation(robots, {"from": win["others_from"]}, exclude=rid)
        base_pct = honest_starvation(base_robots, {"from": win["others_from"]}, exclude=rid) if baseline else None
    else:
        attack_pct = honest_starvation(robots, win)
        base_pct = honest_starvation(base_robots, win) if baseline else None
    row["honest_pct"], row["baseline_pct"] = attack_pct, base_pct
    row["delta_pp"] = (attack_pct - base_pct) if (attack_pct is not None and base_pct is not None) else None
    if row["delta_pp"] is not None and row["delta_pp"] > cfg.tolerance_pp:
        failures.append(f"honest starvation {attack_pct:.1f}% vs {base_pct:.1f}% baseline (+{row['delta_pp']:.1f} pp)")
    if spec.scenario in JOIN:
        firsts = {r["robot_id"]: r.get("first_chunk_s") for r in robots}
        missing = [f"honest{k}" for k in range(HONEST) if firsts.get(f"honest{k}") is None]
        row["join_s"] = None if missing else max(firsts.values())
        limit = JOIN[spec.scenario]
        if missing:
            failures.append(f"never served: {', '.join(missing)}")
        elif row["join_s"] > limit:
            failures.append(f"honest robots joined after {row['join_s']:.1f} s (limit {limit:g} s)")
    growth, peak = record.get("rss_growth_mib"), record.get("rss_peak_growth_mib")
    row["rss_growth_mib"], row["rss_peak_growth_mib"] = growth, peak
    if growth is not None and growth >= cfg.rss_limit_mib:
        failures.append(f"server RSS +{growth:.0f} MiB at the end of the attack (limit {cfg.rss_limit_mib:g})")
    elif peak is not None and peak >= cfg.rss_limit_mib:
        failures.append(f"server RSS peaked at +{peak:.0f} MiB during the attack (limit {cfg.rss_limit_mib:g})")
    violations = record.get("attack", {}).get("violations", {})
    row["violations"] = violations
    for text, n in list(violations.items())[:4]:
        failures.append(f"{text}" + (f" (x{n})" if n > 1 else ""))
    if len(violations) > 4:
        failures.append(f"... {len(violations) - 4} more violation(s)")
    errors = [f"{r['robot_id']}: {r['error']}" for r in robots if r.get("error")]
    if len(robots) < HONEST:
        errors.append(f"{HONEST - len(robots)} honest robot(s) wrote no stats (group exit {record.get('group_exit_code')})")
    if errors:
        failures.append("honest robot failed: " + "; ".join(e[:160] for e in errors[:2]))
    exceptions = record.get("server_exceptions") or {}
    if exceptions:
        top, n = next(iter(exceptions.items()))
        notes.append(f"server logged {sum(exceptions.values())} exception(s), e.g. {top[:140]} (x{n})")
    if record.get("machine_busy_pct", 0) > 90:
        notes.append(f"machine {record['machine_busy_pct']:.0f}% busy")
    extra = record.get("attack", {}).get("extra", {})
    if spec.scenario in SHARE_SCENARIOS:
        base_extra = (baseline or {}).get("attack", {}).get("extra", {})
        share_row(row, extra, robots, base_robots, cfg, failures, notes, limit=spec.scenario == "share_liar", base_extra=base_extra)
    if spec.scenario == "priority_flood" and "granted weight" in extra:
        notes.append(f"granted weight {extra['granted weight']:g}")
    if spec.scenario == "never_reads" and "sent MiB" in extra:
        notes.append(f"sent {extra['sent MiB']:.0f} MiB unread-answer bait")
    if spec.scenario == "idle_sockets":
        notes.append(f"{extra.get('connected', '?')} idle sockets")
    if spec.scenario == "openpi_garbage":
        notes.append(f"{extra.get('garbage frames', '?')} garbage frames")
    if spec.scenario == "openpi_never_reads":
        counts = record.get("attack", {}).get("counts", {})
        standin = (baseline or {}).get("attack", {}).get("counts", {})
        row["requests_sent"] = counts.get("requests sent")
        row["unread_reply_bytes"] = extra.get("unread reply bytes (open connections)")
        # Chunks the server sent each openpi connection over the run, by its own count: the
        # attacker's against the stand-in clients' that read them.
        row["attacker_chunks"] = openpi_chunks(record)
        row["standin_chunks"] = openpi_chunks(baseline or {})
        notes.append(
            f"{counts.get('requests sent', 0)} requests on {counts.get('connections opened', 0)} connection(s), never read "
            f"({fmt(row['unread_reply_bytes'], '.0f')} reply bytes unread at the end); "
            f"{counts.get('connections ended by the server', 0)} ended by the server; chunks served per connection: "
            f"attacker {', '.join(f'{c:.0f}' for c in row['attacker_chunks']) or '-'}, "
            f"stand-in clients {', '.join(f'{c:.0f}' for c in row['standin_chunks']) or '-'} (they read {standin.get('chunks', '-')})"
        )
    if spec.scenario == "openpi_idle":
        notes.append(f"{extra.get('connected', '?')} idle openpi connections, {extra.get('told and closed by the server', '?')} closed by the server")
    if record.get("attack", {}).get("extra", {}).get("attacker error"):
        notes.append("attacker error: " + extra["attacker error"][:120])
    row["passed"] = not failures
    row["failures"] = failures
    row["notes"] = notes
    row["attack_summary"] = record.get("attack_summary", "")
    row["machine_busy_pct"] = record.get("machine_busy_pct")
    return row


def openpi_chunks(record: dict[str, Any]) -> list[float]:
    """Chunks the server sent each openpi session of a run (scraped at the end of its window)."""
    served = record.get("chunks_served")
    return sorted((v for k, v in served.items() if k.startswith("openpi-")), reverse=True) if isinstance(served, dict) else []


def chunks_per_s(robots: list[dict[str, Any]], robot_id: str, start: float) -> float | None:
    """One robot's chunks per second from ``start`` (seconds after the honest robots started)."""
    r = next((r for r in robots if r["robot_id"] == robot_id), None)
    if r is None or not r.get("chunks_at_tick"):
        return None
    return adv.Timeline(list(r["tick_times"]), [int(c) for c in r["executed"]], None, list(r["chunks_at_tick"])).chunks_per_s(start)


def share_row(
    row: dict[str, Any], extra: dict[str, Any], robots: list[dict[str, Any]], base_robots: list[dict[str, Any]], cfg: Config,
    failures: list[str], notes: list[str], limit: bool = True, base_extra: dict[str, Any] | None = None,
) -> None:
    """share_liar: the liar's chunks/s against, in the same run and with the same registration,
    its lean twin (an honest robot of the liar's own client: the two differ only by the lie; the
    row's measure) and the armory_sim twin (another client too), with the baseline's stand-in for
    reference. ``limit``: a lean ratio above ``SHARE_LIMIT`` fails the row (not for the honest
    control share_lean, run on its own, whose ratio to the armory_sim twin is what a lean client
    gets)."""
    liar = extra.get("chunks/s")
    lean = extra.get("lean chunks/s")
    twin = chunks_per_s(robots, "twin", cfg.warmup_s) or 0.0
    # The baseline's stand-in: an armory_sim robot, or (share_liar) an honest lean client.
    standin = chunks_per_s(base_robots, "standin", cfg.warmup_s) or (base_extra or {}).get("chunks/s")
    row["liar_chunks_per_s"], row["twin_chunks_per_s"], row["standin_chunks_per_s"] = liar, twin, standin
    row["lean_twin_chunks_per_s"] = lean
    row["share_ratio"] = liar / twin if (liar is not None and twin) else None
    row["lean_ratio"] = liar / lean if (liar is not None and lean) else None
    measure = row["lean_ratio"] if limit else row["share_ratio"]
    if measure is None:
        failures.append("share not measured (no chunks for the liar or its twin)")
        return
    if limit and measure > SHARE_LIMIT:
        failures.append(f"liar got {liar:.2f} chunks/s vs {lean:.2f} for its lean honest twin ({measure:.2f}x > {SHARE_LIMIT:g}x)")
    ref = f", stand-in in the baseline {standin:.2f}" if standin is not None else ""
    if limit:
        notes.append(
            f"liar {liar:.2f} vs lean honest twin {lean:.2f} chunks/s ({measure:.2f}x); armory_sim twin {twin:.2f} "
            f"(liar {row['share_ratio'] or float('nan'):.2f}x, lean twin {lean / twin if twin else float('nan'):.2f}x){ref}"
        )
    else:
        notes.append(f"lean honest client {liar:.2f} vs honest twin {twin:.2f} chunks/s ({measure:.2f}x){ref}")


# ---- planning and reporting ----------------------------------------------------------------------


def token_file(work: Path) -> tuple[Path, dict[str, Any]]:
    """A token file: one fleet token and a per-robot token for each honest robot, the victim and
    a reserved id."""
    tokens = {f"honest{k}": f"honest{k}-token-{k}0123456789abcdef" for k in range(HONEST)}
    fleet = "fleet-token-0123456789abcdef"
    extra = {"victim": "victim-token-0123456789abcdef", "reserved": "reserved-token-0123456789abcdef"}
    path = work / "tokens.txt"
    lines = [fleet] + [f"{rid} {tok}" for rid, tok in {**tokens, **extra}.items()]
    path.write_text("\n".join(lines) + "\n")
    kwargs = {
        "fleet_token": fleet, "protected_ids": ("reserved", "honest0"), "victim_id": "victim",
        "victim_token": extra["victim"], "other_token": tokens["honest1"],
    }  # fmt: skip
    return path, {"tokens": tokens, "attack_kwargs": kwargs}


def plan(cfg: Config, work: Path) -> list[RunSpec]:
    """Baselines first (one per scheduler and cap needed), then every scenario row."""
    scenarios = [s.strip() for s in cfg.scenarios.split(",") if s.strip()]
    unknown = sorted(set(scenarios) - set(ALL_SCENARIOS) - set(CONTROLS))
    if unknown:
        sys.exit(f"adversarial: unknown scenario(s) {', '.join(unknown)}; known: {', '.join(ALL_SCENARIOS)}")
    schedulers = [s.strip() for s in cfg.schedulers.split(",") if s.strip()]
    bad = sorted(set(schedulers) - set(SCHEDULERS))
    if bad or not schedulers:
        sys.exit(f"adversarial: unknown scheduler(s) {', '.join(bad) or '(none)'}; use {', '.join(SCHEDULERS)}")
    single = next((s for s in SINGLE_PREFERENCE if s in schedulers), schedulers[0])
    runs: list[RunSpec] = []
    for name in scenarios:
        scheds = [single] if name in ONCE else schedulers
        if name in SHARE_SCENARIOS and not cfg.quick:
            scheds = [s for s in SCHEDULERS if s in schedulers or s == "rollout"]
        for sched in scheds:
            base = RunSpec(name, sched, attack=None if name == "clock_step" else name)
            if name in SHARE_SCENARIOS:
                base.standin = SHARE_REGISTRATION
                base.duration_s = 2 * cfg.duration_s  # ~50 chunks a robot: a ratio worth reading
            if name == "share_liar":
                # Beside the liar, an honest robot of its own client and registration (lean-twin):
                # the two differ only by the lie. The baseline runs two honest lean clients, in the
                # liar's place and the twin's, so that both runs serve the same robots.
                base.attack_kwargs = {"lean_twin": True}
                base.standin_attack = "share_lean_pair"
            if name == "clock_ahead":
                base.standin = CLOCK_AHEAD_REGISTRATION
            if name == "clock_step":
                runs += [replace(base, variant="+1h", step_s=3600.0), replace(base, variant="-1h", step_s=-3600.0)]
                continue
            if name == "never_reads":
                # ~64 KiB names at 190 obs/s (under the server's 200/s): the window lasts until all is sent.
                base.attack_kwargs = {"total_bytes": int(cfg.never_reads_mib * adv.MIB)}
                per_s = 190.0 * (64 * 1024 + 3 * cfg.image_size**2)
                base.duration_s = max(cfg.duration_s, cfg.never_reads_mib * adv.MIB / per_s + 2.0)
            if name == "slot_squat":
                base.server_args = [f"--max_robots={HONEST + 4}"]
                base.attack_kwargs = {"slots": HONEST + 4}
                base.lead = True
            if name == "idle_sockets":
                base.lead = True
            if name == "openpi_idle":
                port = free_port()
                base.server_args = [f"--max_robots={HONEST + 4}", f"--openpi.port={port}"]
                base.attack_kwargs = {"port": port}
                base.lead = True
            if name == "openpi_never_reads":
                port = free_port()
                base.metrics_port = free_port()
                base.server_args = [f"--openpi.port={port}", f"--metrics_port={base.metrics_port}"]
                base.attack_kwargs = {"port": port, "connections": OPENPI_NEVER_READS_CONNECTIONS}
                if cfg.standin:  # stand-in: as many openpi clients that read their replies
                    base.standin_attack = "openpi_honest"
                    base.standin_kwargs = (("connections", OPENPI_NEVER_READS_CONNECTIONS),)
            if name == "openpi_garbage":
                port = free_port()
                base.server_args = [f"--openpi.port={port}"]
                base.attack_kwargs = {"port": port, "seed": cfg.seed}
            if name == "identity":
                path, auth = token_file(work)
                base.server_args = [f"--auth_token_file={path}"]
                base.tokens = auth["tokens"]
                base.attack_kwargs = auth["attack_kwargs"]
                base.lead = True
            if name in ("capture_absurd", "report_absurd", "garbage"):
                base.attack_kwargs = {"seed": cfg.seed}
            runs.append(base)
            if name == "clock_ahead" and sched == "edf":
                runs.append(replace(base, cap=1))
    needed = {r.baseline_key for r in runs}
    order = {s: k for k, s in enumerate(schedulers)}
    baselines = []
    for s, c, st, sa, sk in sorted(needed, key=lambda p: (order.get(p[0], 9), -p[1], p[2], p[3])):
        b = RunSpec("baseline", s, cap=c, standin=st, duration_s=2 * cfg.duration_s if st else None, standin_attack=sa, standin_kwargs=sk)
        if sa == "share_lean_pair":  # honest lean clients where the liar and its lean twin run
            b.attack, b.attack_kwargs = sa, dict(sk)
        elif sa:  # the stand-in runs where the attacker would, on ports of its own
            port, b.metrics_port = free_port(), free_port()
            b.attack, b.attack_kwargs = sa, {"port": port, **dict(sk)}
            b.server_args = [f"--openpi.port={port}", f"--metrics_port={b.metrics_port}"]
        baselines.append(b)
    return baselines + runs


def free_port() -> int:
    """A TCP port free on the loopback now (for the openpi endpoint of a run)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fmt(x: float | None, spec: str = ".1f", none: str = "-") -> str:
    return none if x is None else format(x, spec)


def table(rows: list[dict[str, Any]]) -> str:
    header = f"{'scenario':<22} {'scheduler':<11} {'up':<4} {'honest starv% (base)':>21} {'Δ pp':>6} {'RSS +MiB (peak)':>16} {'result':<6} note"
    lines = [header, "-" * len(header)]
    for r in rows:
        name = f"{r['scenario']}({r['variant']})" if r.get("variant") else r["scenario"]
        starv = f"{fmt(r.get('honest_pct'))} ({fmt(r.get('baseline_pct'))})"
        rss = f"{fmt(r.get('rss_growth_mib'), '.0f')} ({fmt(r.get('rss_peak_growth_mib'), '.0f')})"
        delta = fmt(r.get("delta_pp"), "+.1f")
        note = "; ".join(r["failures"] + r["notes"])
        lines.append(
            f"{name:<22} {r['scheduler']:<11} {'yes' if r['server_up'] else 'NO':<4} {starv:>21} {delta:>6} {rss:>16} "
            f"{'pass' if r['passed'] else 'FAIL':<6} {note}"
        )
    return "\n".join(lines)


def before_cell(row: dict[str, Any] | None) -> str:
    """A row of an earlier run (``--before``) in one short cell."""
    if row is None:
        return "-"
    if row["passed"]:
        return f"pass ({fmt(row.get('delta_pp'), '+.1f')} pp)"
    first = row["failures"][0] if row["failures"] else "?"
    return "FAIL: " + (first[:90] + "..." if len(first) > 90 else first).replace("|", "\\|")


def markdown(
    rows: list[dict[str, Any]],
    baselines: list[dict[str, Any]],
    cfg: Config,
    command: str,
    elapsed_s: float,
    before: dict[str, dict[str, Any]] | None = None,
) -> str:
    out = [
        "# Adversarial benchmark: one robot cannot hurt the fleet",
        "",
        f"Command: `{command}` ({elapsed_s / 60:.1f} min on this machine).",
        "",
        ("Setup per run: the real `lerobot-armory-server` (planner demo policy, H=10, 64 px camera, "
        f"`--engine.emulate_profile=l40s-pi05`, `--max_batch_size={CAP}` unless the row says b=1), "
        f"{HONEST} honest `armory_sim` robots (20 fps, h_min 5, h_max 10, weight 1, emulated network "
        "3.75 ms median, libero jitter) in one process, and one attacker speaking the raw protocol "
        "(`tests/support/adversaries.py`); each baseline serves one more honest robot in the attacker's place "
        "(not measured), unless `--no_standin`. Honest robots tick for "
        f"{cfg.warmup_s:g} s + {cfg.duration_s:g} s; the attacker starts after the warm-up, or "
        f"{LEAD_S:g} s before the honest robots for slot_squat, identity, idle_sockets and openpi_idle "
        "(1,000 websocket connections to the openpi port that never ask; the server has room for "
        f"{HONEST + 4} robots). openpi_never_reads: {OPENPI_NEVER_READS_CONNECTIONS} openpi connections send valid "
        "requests as fast as the server takes them and never read a reply; its baseline's stand-in is "
        f"{OPENPI_NEVER_READS_CONNECTIONS} openpi clients that read each reply and ask again at once."),
        "",
        ("A row passes when the server is up at the end of the attack (alive, health SERVING), the "
        f"honest robots' starvation over the attack window is at most {cfg.tolerance_pp:g} pp above the "
        f"baseline's (same scheduler, same window), the server's RSS grew less than {cfg.rss_limit_mib:g} MiB (at the end of the attack and at its peak), "
        "the attacker saw no rule broken (violations), every honest robot ran, and the server still stops "
        "on SIGTERM within 15 s. slot_squat, idle_sockets and openpi_idle: starvation from each "
        "robot's first chunk, and all joined within "
        f"{JOIN['slot_squat']:g} s / {JOIN['idle_sockets']:g} s / {JOIN['openpi_idle']:g} s. clock_step: the stepped robot from "
        f"{STEP_SETTLE_S:g} s after the step against its own baseline, the others from the step."),
        "",
        "## Results",
        "",
        "| scenario | scheduler | server up | honest starvation % (baseline) | Δ pp | RSS growth MiB (peak) | result | note |"
        + (" before |" if before else ""),
        "|---|---|---|---|---|---|---|---|" + ("---|" if before else ""),
    ]
    for r in rows:
        name = f"{r['scenario']}({r['variant']})" if r.get("variant") else r["scenario"]
        note = "; ".join(r["failures"] + r["notes"]).replace("|", "\\|")
        out.append(
            f"| {name} | {r['scheduler']} | {'yes' if r['server_up'] else '**NO**'} | {fmt(r.get('honest_pct'))} "
            f"({fmt(r.get('baseline_pct'))}) | {fmt(r.get('delta_pp'), '+.1f')} | {fmt(r.get('rss_growth_mib'), '.0f')} "
            f"({fmt(r.get('rss_peak_growth_mib'), '.0f')}) | {'pass' if r['passed'] else '**FAIL**'} | {note} |"
            + (f" {before_cell(before.get(r['label']))} |" if before else "")
        )
    if before:
        out += ["", f"The *before* column: the same benchmark on {cfg.before_label or cfg.before}.", ""]
    out += ["", "## Baselines (no attacker)", "", "| scheduler | honest starvation % (whole run) | from warm-up | server RSS MiB |", "|---|---|---|---|"]
    for b in baselines:
        out.append(
            f"| {b['scheduler']} | {fmt(honest_starvation(b['robots'], {'from': 0.0}))} | "
            f"{fmt(honest_starvation(b['robots'], {'from': cfg.warmup_s}))} | {fmt(b.get('rss_end_mib'), '.0f')} |"
        )
    out += ["", "## What each attacker did", ""]
    for r in rows:
        out.append(f"- **{r['label']}**: {r['attack_summary'] or 'no attacker'}")
    failed = [r for r in rows if not r["passed"]]
    out += ["", f"{len(rows) - len(failed)} of {len(rows)} rows pass." + (" Failing: " + ", ".join(r["label"] for r in failed) if failed else ""), ""]
    return "\n".join(out)


def parse(argv: list[str] | None) -> Config:
    global HONEST
    p = argparse.ArgumentParser(prog="benchmarks/adversarial.py", description=__doc__.split("\n\n")[0])
    d = Config()
    p.add_argument("--scenarios", default=None, help=f"comma-separated (default: all: {','.join(ALL_SCENARIOS)})")
    p.add_argument("--schedulers", default=None, help="comma-separated of rr, edf, lookahead, rollout (default: rr, edf, lookahead; share_liar adds rollout; --quick: lookahead)")
    p.add_argument("--duration_s", type=float, default=None, help=f"attack window per run (default {d.duration_s:g}; --quick 5)")
    p.add_argument("--warmup_s", type=float, default=None, help=f"honest robots run alone first (default {d.warmup_s:g}; --quick 1)")
    p.add_argument("--output_dir", default=None, help=f"README.md and results.json (default {d.output_dir}; --quick out/adversarial-quick)")
    p.add_argument("--quick", action="store_true", help="development: one scheduler, short runs, 60 MiB for never_reads")
    p.add_argument("--tolerance_pp", type=float, default=d.tolerance_pp)
    p.add_argument("--rss_limit_mib", type=float, default=d.rss_limit_mib)
    p.add_argument("--never_reads_mib", type=float, default=None)
    p.add_argument("--image_size", type=int, default=d.image_size)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--policy_path", default=None)
    p.add_argument("--work_dir", default=None, help="where run files go (default: a temporary directory)")
    p.add_argument("--server_nofile", type=int, default=d.server_nofile, help="soft fd limit the server starts with (default 1024, the usual default; 0: inherit)")
    p.add_argument("--before_label", default=None, help="what the --before run served (README.md), e.g. a commit")
    p.add_argument("--before", default=None, help="results.json of an earlier run: README.md shows its verdict beside each row")
    p.add_argument("--no_standin", action="store_true", help="baselines without an honest robot in the attacker's place")
    p.add_argument("--honest", type=int, default=HONEST,
                   help=f"honest robots per run (default {HONEST}: a lightly loaded fleet; more saturate the device, so that "
                        "what an attacker takes shows as honest starvation)")  # fmt: skip
    a = p.parse_args(argv)
    if a.honest < 1:
        p.error("--honest must be >= 1")
    HONEST = a.honest
    q = a.quick
    return Config(
        scenarios=a.scenarios or d.scenarios,
        schedulers=a.schedulers or ("lookahead" if q else d.schedulers),
        duration_s=a.duration_s if a.duration_s is not None else (5.0 if q else d.duration_s),
        warmup_s=a.warmup_s if a.warmup_s is not None else (1.0 if q else d.warmup_s),
        output_dir=a.output_dir or ("out/adversarial-quick" if q else d.output_dir),
        quick=q,
        image_size=a.image_size,
        tolerance_pp=a.tolerance_pp,
        rss_limit_mib=a.rss_limit_mib,
        never_reads_mib=a.never_reads_mib if a.never_reads_mib is not None else (60.0 if q else d.never_reads_mib),
        seed=a.seed,
        policy_path=a.policy_path,
        work_dir=a.work_dir,
        before=a.before,
        server_nofile=a.server_nofile,
        before_label=a.before_label,
        standin=not a.no_standin,
    )


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    t_start = time.monotonic()
    work = Path(cfg.work_dir or tempfile.mkdtemp(prefix="armory-adversarial-"))
    work.mkdir(parents=True, exist_ok=True)
    runs = plan(cfg, work)
    before = None
    if cfg.before:  # read first: a bad path fails now, not after the runs
        before = {r["label"]: r for r in json.loads(Path(cfg.before).read_text())["rows"]}
    policy = ensure_policy(cfg)
    adv.raise_fd_limit(4096)
    print(
        f"adversarial bench: {len(runs)} runs ({cfg.warmup_s:g} s + {cfg.duration_s:g} s each), {HONEST} honest robots, "
        f"schedulers {cfg.schedulers}; work dir {work}",
        flush=True,
    )
    baselines: dict[tuple, dict[str, Any]] = {}
    rows: list[dict[str, Any]] = []
    records: list[dict[str, Any]] = []
    for k, spec in enumerate(runs, start=1):
        t0 = time.monotonic()
        try:
            record = run_once(spec, cfg, policy, work)
        except Exception as exc:  # noqa: BLE001 - one broken run is a failed row, not a dead bench
            record = {"label": spec.label, "scenario": spec.scenario, "variant": spec.variant, "scheduler": spec.sched_label,
                      "server_alive": False, "server_healthy": False, "server_crash": [f"run failed: {type(exc).__name__}: {exc}"], "robots": []}  # fmt: skip
        records.append(record)
        took = time.monotonic() - t0
        if spec.scenario == "baseline":
            baselines[spec.baseline_key] = record
            pct = honest_starvation(record["robots"], {"from": cfg.warmup_s})
            errs = [r["error"] for r in record["robots"] if r.get("error")]
            print(
                f"[{k}/{len(runs)}] baseline / {spec.sched_label}: honest starvation {fmt(pct)}% after warm-up, "
                f"server RSS {fmt(record.get('rss_end_mib'), '.0f')} MiB, up={record.get('server_alive')}"
                f"{' ERRORS: ' + '; '.join(errs) if errs else ''} ({took:.0f} s)",
                flush=True,
            )
            continue
        row = judge(spec, record, baselines.get(spec.baseline_key), cfg)
        rows.append(row)
        print(
            f"[{k}/{len(runs)}] {spec.label}: {'pass' if row['passed'] else 'FAIL'} — up={'yes' if row['server_up'] else 'NO'}, "
            f"honest {fmt(row.get('honest_pct'))}% vs {fmt(row.get('baseline_pct'))}% ({fmt(row.get('delta_pp'), '+.1f')} pp), "
            f"RSS {fmt(row.get('rss_growth_mib'), '+.0f')} MiB"
            + (f", joined in {fmt(row.get('join_s'))} s" if spec.scenario in JOIN else "")
            + (f" — {'; '.join(row['failures'])}" if row["failures"] else "")
            + f" ({took:.0f} s)",
            flush=True,
        )
    elapsed = time.monotonic() - t_start
    print()
    print(table(rows))
    failed = [r for r in rows if not r["passed"]]
    print(f"\n{len(rows) - len(failed)} of {len(rows)} rows pass ({elapsed / 60:.1f} min)")
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    command = "benchmarks/adversarial.py " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    base_list = [
        {**b, "scheduler": RunSpec("baseline", s, cap=c, standin=st, standin_attack=sa, standin_kwargs=sk).sched_label}
        for (s, c, st, sa, sk), b in baselines.items()
    ]
    (out / "README.md").write_text(markdown(rows, base_list, cfg, command, elapsed, before))
    slim = [{k: v for k, v in r.items() if k != "robots"} | {"robots": [_slim(x) for x in r.get("robots", [])]} for r in records]
    (out / "results.json").write_text(json.dumps({"command": command, "config": cfg.__dict__, "rows": rows, "runs": slim}, indent=1, default=str) + "\n")
    print(f"wrote {out / 'README.md'} and {out / 'results.json'}")
    return 1 if failed else 0


def _slim(stats: dict[str, Any]) -> dict[str, Any]:
    """A robot's stats for results.json: the timeline kept compact."""
    s = {k: v for k, v in stats.items() if k not in ("tick_times", "first_executed_index")}
    return s


if __name__ == "__main__":
    sys.exit(main())

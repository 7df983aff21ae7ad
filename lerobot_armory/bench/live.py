"""``lerobot-armory-bench``: the real server and a simulated fleet over the real protocol.

For each scheduler (and seed) it starts ``lerobot-armory-server`` (optionally with an emulated
latency profile) and a few processes of ``armory_sim`` robots (fast robots on the dynamic scene,
slow robots on the static one, timing from the preset), runs them for ``duration_s``, collects
every robot's stats and the server's batch log, and reports per-tier starvation and successes
per minute beside the discrete-event simulator's prediction for the same fleet, profile and
network (mirror fidelity). CPU use of all processes is measured, and a run that saturated the
machine is flagged: then starvation measures the benchmark machine, not the scheduler.

    lerobot-armory-bench --preset=libero --mix=half-fast --robots=4 --schedulers=rr,edf,lookahead \\
        --fast_weight=3 --emulate_profile=l40s-pi05 --duration_s=20
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.robot_spec import TIERS
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.presets import MIXES, fleet_specs, get_preset
from lerobot_armory.sim.run import run_label
from lerobot_armory.sim.simulator import FleetSimulator

SATURATED_PCT = 90.0


@dataclass
class BenchConfig:
    """Options of ``lerobot-armory-bench``.

    Attributes:
        preset: robot timing (``libero`` or ``piper``; docs/spec.md §5).
        mix: which robots are fast: all-fast, one-fast, half-fast.
        robots: fleet size N.
        schedulers: comma-separated schedulers to compare: ``rr``, ``edf``, ``lookahead`` (uses
            ``fast_weight``), or ``lookahead@W`` for fast weight W (``lookahead@1,lookahead@5``).
        fast_weight: weight of fast robots where a scheduler entry gives none.
        depth: Lookahead depth L.
        max_batch_size: batch cap (default: the preset's).
        emulate_profile: latency profile the server replays (``--engine.emulate_profile``); empty:
            the real model's timing on this machine (the server profiles it at start-up and the
            simulator replays that measured profile).
        device: ``--policy.device`` of the server (``cpu``, ``cuda``).
        policy_args: more ``--policy.<field>=value`` options for the server, space-separated
            (``--policy.dtype=bfloat16 --policy.compile_model=true``).
        net_median_ms / net_sigma: client-side emulated one-way delay (log-normal per message).
        duration_s: seconds per run.
        seeds: runs per scheduler (seed 0, 1, ...).
        wait_ms: every scheduler's dispatch timing (``--scheduler.wait_ms``; 0: work-conserving).
        policy_path: policy to serve (default: the analytic armory_planner, built if missing).
        groups: robot processes (robots are spread over them).
        image_size: camera size of the simulated robots.
        output: write the runs as JSON here.
        work_dir: where stats and batch logs go (default: a temporary directory).
    """

    preset: str = "libero"
    mix: str = "half-fast"
    robots: int = 4
    schedulers: str = "rr,edf,lookahead"
    fast_weight: float = 3.0
    depth: int = 1
    max_batch_size: int | None = None
    emulate_profile: str = "l40s-pi05"
    device: str = "cpu"
    policy_args: str = ""
    net_median_ms: float = 0.0
    net_sigma: float = 0.0
    duration_s: float = 20.0
    seeds: int = 1
    wait_ms: float = 0.0
    policy_path: str | None = None
    groups: int = 2
    image_size: int = 64
    output: str | None = None
    work_dir: str | None = None


def parse_entry(entry: str, default_weight: float) -> tuple[str, float]:
    """``"lookahead@3"`` -> ("lookahead", 3.0); ``"edf"`` -> ("edf", default weight)."""
    name, _, weight = entry.strip().partition("@")
    make_scheduler_config(name)  # ConfigError if unknown
    try:
        w = float(weight) if weight else default_weight
    except ValueError:
        raise ConfigError("schedulers", f"bad weight in {entry!r}; write e.g. lookahead@3") from None
    if not w > 0:
        raise ConfigError("schedulers", f"weight must be > 0 in {entry!r}")
    return name, w


def ensure_policy(cfg: BenchConfig, chunk_size: int) -> str:
    """The policy directory to serve; builds the planner for this chunk size if none given."""
    if cfg.policy_path:
        return cfg.policy_path
    path = Path("out") / f"planner-H{chunk_size}-S{cfg.image_size}"
    if not (path / "config.json").is_file():
        from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

        make_demo_policy(DemoPolicyConfig(output=str(path), kind="planner", chunk_size=chunk_size, image_size=cfg.image_size))
    return str(path)


def machine_cpu() -> tuple[float, float]:
    """(busy, total) jiffies of the whole machine, from /proc/stat."""
    try:
        fields = [float(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return 0.0, 0.0
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)
    return sum(fields) - idle, sum(fields)


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of ``pid`` (all its threads), from /proc/PID/stat (0 if gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def start_server(args: list[str]) -> tuple[subprocess.Popen, str]:
    """``lerobot-armory-server`` with ``args`` in a subprocess; returns it and its address once it listens."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "lerobot_armory.entrypoints.server", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    lines = []
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        line = proc.stdout.readline() if proc.stdout else ""
        if not line:
            break
        lines.append(line)
        if "listening on" in line:
            return proc, line.split("listening on")[1].strip()
    proc.kill()
    raise RuntimeError("the server did not start:\n" + "".join(lines[-20:]))


def stop_all(server: subprocess.Popen, procs: list[subprocess.Popen]) -> None:
    """Kill the robot processes still running, then stop the server (SIGTERM, killed after 30 s)."""
    for p in procs:
        if p.poll() is None:
            p.kill()
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=30)
    except subprocess.TimeoutExpired:
        server.kill()


def run_live(cfg: BenchConfig, scheduler: str, seed: int, work: Path) -> dict[str, Any]:
    """One live run: server + robot groups; returns its run record."""
    preset = get_preset(cfg.preset)
    cap = cfg.max_batch_size or preset.default_batch_cap(cfg.mix)
    specs = fleet_specs(preset, cfg.mix, cfg.robots, cfg.fast_weight)
    policy = ensure_policy(cfg, preset.chunk_size)
    run_dir = work / f"{cfg.preset}-{cfg.mix}-N{cfg.robots}-{scheduler}-w{cfg.fast_weight:g}-wait{cfg.wait_ms:g}-seed{seed}"
    (run_dir / "stats").mkdir(parents=True, exist_ok=True)
    batch_log = run_dir / "batches.jsonl"
    args = [
        f"--policy.path={policy}", f"--policy.device={cfg.device}", "--port=0", f"--scheduler.type={scheduler}",
        f"--max_batch_size={cap}", f"--batch_log={batch_log}", "--status_interval_s=0", "--log_level=warning",
        *shlex.split(cfg.policy_args),
    ]  # fmt: skip
    # The operator grants the weights the bench's robots ask for (without a policy every weight is 1).
    policy_file = run_dir / "grant_rules.json"
    policy_file.write_text(json.dumps({"robots": {s.robot_id: {"max_weight": s.weight} for s in specs if s.weight != 1.0}}))
    args.append(f"--fleet.rules={policy_file}")
    measured = run_dir / "profile.json"  # real timing: profiled at start-up, saved, replayed by the simulator
    if scheduler == "lookahead":
        args.append(f"--scheduler.depth={cfg.depth}")
    if cfg.wait_ms > 0:
        args.append(f"--scheduler.wait_ms={cfg.wait_ms:g}")
    if cfg.emulate_profile:
        args.append(f"--engine.emulate_profile={cfg.emulate_profile}")
    else:
        measured.unlink(missing_ok=True)
        args.append(f"--latency_profile={measured}")
    server, address = start_server(args)
    before = os.times()
    reaped_before = before.children_user + before.children_system
    groups = max(1, min(cfg.groups, cfg.robots))
    procs = []
    try:
        for g in range(groups):
            robots = [
                {
                    "robot_id": s.robot_id, "tier": s.tier, "scene": "dynamic" if s.tier == "fast" else "static",
                    "fps": s.fps, "h_min": s.h_min, "h_max": s.h_max, "weight": s.weight, "seed": 1000 * seed + k,
                }
                for k, s in enumerate(specs) if k % groups == g
            ]  # fmt: skip
            spec_path = run_dir / f"group{g}.json"
            spec_path.write_text(
                json.dumps(
                    {
                        "address": address, "duration_s": cfg.duration_s, "stats_dir": str(run_dir / "stats"),
                        "robots": robots, "net_median_ms": cfg.net_median_ms, "net_sigma": cfg.net_sigma,
                        "image_size": cfg.image_size,
                    }
                )
            )  # fmt: skip
            procs.append(subprocess.Popen([sys.executable, "-m", "lerobot_armory.bench.robots", str(spec_path)]))
        # CPU over the run (after start-up): /proc while processes live, the kernel's account of
        # reaped children (os.times) once the robot groups have exited.
        time.sleep(min(cfg.duration_s / 4, 2.0))
        t_mid = time.monotonic()
        machine_mid = machine_cpu()
        server_mid, groups_mid = cpu_seconds(server.pid), sum(cpu_seconds(p.pid) for p in procs)
        codes = [p.wait(timeout=cfg.duration_s + 120) for p in procs]
        reaped = os.times()
        groups_total = reaped.children_user + reaped.children_system - reaped_before
        used = (cpu_seconds(server.pid) - server_mid) + (groups_total - groups_mid)
        cpu_pct = 100.0 * used / max(1e-9, time.monotonic() - t_mid) / (os.cpu_count() or 1)
        machine_end = machine_cpu()
        # The whole machine, not just our processes: anything else running skews the robots' clocks.
        machine_pct = 100.0 * (machine_end[0] - machine_mid[0]) / max(1e-9, machine_end[1] - machine_mid[1])
    finally:
        stop_all(server, procs)
    if any(codes):
        raise RuntimeError(f"robot group(s) failed with exit codes {codes}; see the messages above")
    stats = [json.loads(p.read_text()) for p in sorted((run_dir / "stats").glob("*.json"))]
    batches = [json.loads(line) for line in batch_log.read_text().splitlines() if line.strip()]
    profile = load_profile(cfg.emulate_profile or str(measured))
    record = _record(cfg, scheduler, seed, cap, stats, batches, cpu_pct, profile)
    record["machine_busy_pct"] = machine_pct
    record["saturated"] = machine_pct > SATURATED_PCT
    return record


def _record(
    cfg: BenchConfig, scheduler: str, seed: int, cap: int, stats: list[dict], batches: list[dict], cpu_pct: float, profile: LatencyProfile
) -> dict[str, Any]:
    tiers: dict[str, dict[str, float]] = {}
    for tier in TIERS:
        rows = [s for s in stats if s["tier"] == tier]
        if rows:
            tiers[tier] = {
                "robots": len(rows),
                "starvation_pct": float(np.mean([s["starvation_pct"] for s in rows])),
                "executed_s": float(sum(s["executed_steps"] / s["fps"] for s in rows)),
                "successes_per_min": float(np.mean([s["successes_per_min"] for s in rows])),
                # The robots' own seam measurement (robot/actions.py): action jump at chunk switches.
                "seam_jump_mean": _mean_of(rows, "seam_jump_mean"),
                "seam_jump_p95": _mean_of(rows, "seam_jump_p95"),
                "action_jerk_mean": _mean_of(rows, "action_jerk_mean"),  # armory_sim's own measure
            }
    sizes: dict[str, int] = {}
    for b in batches:
        sizes[str(len(b["robots"]))] = sizes.get(str(len(b["robots"])), 0) + 1
    decisions = sorted(b["decision_ms"] for b in batches) or [0.0]
    overhead_ms = batch_overhead_ms(batches, profile)
    profile_label = f"{cfg.emulate_profile} (emulated latency)" if cfg.emulate_profile else f"real model timing on {cfg.device}"
    return {
        "live": True,
        "scheduler": scheduler,
        "label": run_label(scheduler, cfg.fast_weight, cfg.depth) + (f" +wait {cfg.wait_ms:g} ms" if cfg.wait_ms > 0 else ""),
        "wait_ms": cfg.wait_ms,
        "preset": cfg.preset,
        "mix": cfg.mix,
        "robots": cfg.robots,
        "seed": seed,
        "max_batch_size": cap,
        "fast_weight": cfg.fast_weight,
        "latency_profile": profile_label,
        "latency_profile_ms": list(profile.latency_ms),
        "net_median_ms": cfg.net_median_ms,
        "net_sigma": cfg.net_sigma,
        "duration_s": cfg.duration_s,
        "avg_starvation_pct": float(np.mean([s["starvation_pct"] for s in stats])),
        "tiers": tiers,
        "executed_s": float(sum(s["executed_steps"] / s["fps"] for s in stats)),
        "batch_sizes": dict(sorted(sizes.items(), key=lambda kv: int(kv[0]))),
        "decision_ms_p99": float(decisions[min(len(decisions) - 1, int(0.99 * len(decisions)))]),
        "cpu_busy_pct": cpu_pct,
        "batch_overhead_ms": overhead_ms,
        "saturated": False,
        "per_robot": stats,
    }


def _mean_of(rows: list[dict], key: str) -> float | None:
    """Mean of ``key`` over the robots that measured it (None: no robot did)."""
    values = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(values)) if values else None


def batch_overhead_ms(batches: list[dict], profile: LatencyProfile) -> float:
    """Measured serving overhead per batch: time a batch took beyond the profile, plus the gap
    to the next batch when they ran back to back (a request was waiting). The simulator adds it
    to model the live server (docs/spec.md §5 mirror fidelity)."""
    if not batches:
        return 0.0
    ordered = sorted(batches, key=lambda b: b["t_start"])
    excess = [b["t_end"] - b["t_start"] - profile.latency_s(len(b["robots"])) for b in ordered]
    gaps = [n["t_start"] - p["t_end"] for p, n in zip(ordered, ordered[1:], strict=False) if n["t_start"] - p["t_end"] < 0.02]
    return 1000.0 * (float(np.mean(excess)) + (float(np.mean(gaps)) if gaps else 0.0))


def simulate_same(
    cfg: BenchConfig, scheduler: str, seed: int, overhead_ms: float = 0.0, profile: LatencyProfile | None = None
) -> dict[str, float]:
    """The simulator's per-tier starvation for the live run's fleet, profile and network;
    ``overhead_ms`` adds the live server's measured per-batch serving overhead to the batches'
    real duration (the scheduler still plans with the nominal profile, as the live one does).
    ``profile``: the run's (emulated, or measured by the server at start-up); default: the
    emulated profile or the preset's."""
    preset = get_preset(cfg.preset)
    cap = cfg.max_batch_size or preset.default_batch_cap(cfg.mix)
    profile = profile or load_profile(cfg.emulate_profile or preset.latency_profile)
    sched_cfg = make_scheduler_config(scheduler, wait_ms=cfg.wait_ms)
    if scheduler == "lookahead":
        sched_cfg = replace(sched_cfg, depth=cfg.depth)
    specs = fleet_specs(preset, cfg.mix, cfg.robots, cfg.fast_weight)
    net = LogNormalDelay(cfg.net_median_ms / 1000.0, cfg.net_sigma)
    true = None
    if overhead_ms > 0:
        true = LatencyProfile(f"{profile.name}+{overhead_ms:.1f}ms", tuple(v + overhead_ms for v in profile.latency_ms), profile.device)
    result = FleetSimulator(specs, sched_cfg.make(profile, cap), cfg.duration_s, net, net, seed, true_latency=true).run()
    return {tier: result.tier_starvation_pct(tier) for tier in TIERS if result.tier(tier)}


def table(runs: list[dict[str, Any]]) -> str:
    """Per-tier starvation (live vs simulated with the measured per-batch overhead) and successes
    per minute, one row per run."""
    header = (
        f"{'scheduler':<12} {'seed':>4} {'fast starv% live/sim':>21} {'slow starv% live/sim':>21} "
        f"{'succ/min fast':>13} {'succ/min slow':>13} {'seam fast/slow':>14} {'mean b':>6} {'ovh ms':>6} {'cpu% bench/machine':>18}"
    )
    lines = [header, "-" * len(header)]
    for r in runs:
        cells = []
        for tier in TIERS:
            live = r["tiers"].get(tier)
            sim = r.get("sim", {}).get(tier)
            cells.append("-" if live is None else f"{live['starvation_pct']:6.1f} / {sim:5.1f}" if sim is not None else f"{live['starvation_pct']:6.1f}")
        succ = [f"{r['tiers'][t]['successes_per_min']:.1f}" if t in r["tiers"] else "-" for t in TIERS]
        seams = [r["tiers"].get(t, {}).get("seam_jump_mean") for t in TIERS]
        seam = "/".join("-" if v is None else f"{v:.3f}" for v in seams)
        sizes = {int(k): v for k, v in r["batch_sizes"].items()}
        mean_b = sum(k * v for k, v in sizes.items()) / max(1, sum(sizes.values()))
        flag = " SATURATED" if r["saturated"] else ""
        lines.append(
            f"{r['label']:<12} {r['seed']:>4} {cells[0]:>21} {cells[1]:>21} {succ[0]:>13} {succ[1]:>13} {seam:>14} {mean_b:>6.2f} "
            f"{r.get('batch_overhead_ms', 0.0):>6.1f} {r['cpu_busy_pct']:>9.0f}/{r.get('machine_busy_pct', 0.0):<8.0f}{flag}"
        )
    return "\n".join(lines)


def run(cfg: BenchConfig) -> list[dict[str, Any]]:
    """Every scheduler × seed, live and simulated; prints the table, writes JSON."""
    get_preset(cfg.preset)
    if cfg.mix not in MIXES:
        raise ConfigError("mix", f"unknown mix {cfg.mix!r}; known: {', '.join(MIXES)}")
    if cfg.robots < 1 or cfg.duration_s <= 0 or cfg.seeds < 1:
        raise ConfigError("robots", "robots, duration_s and seeds must be positive")
    entries = [parse_entry(e, cfg.fast_weight) for e in cfg.schedulers.split(",") if e.strip()]
    if cfg.emulate_profile:
        load_profile(cfg.emulate_profile)
    work = Path(cfg.work_dir or tempfile.mkdtemp(prefix="armory-bench-"))
    label = f"{cfg.emulate_profile} (emulated latency)" if cfg.emulate_profile else f"real model timing on {cfg.device}"
    total = len(entries) * cfg.seeds
    print(
        f"live bench: {cfg.robots} armory_sim robots ({cfg.preset} timing, {cfg.mix}), profile {label}, "
        f"network {cfg.net_median_ms:g} ms/σ={cfg.net_sigma:g}, {cfg.duration_s:g} s per run, {total} run(s)",
        flush=True,
    )
    runs = []
    for k, ((scheduler, weight), seed) in enumerate((e, seed) for e in entries for seed in range(cfg.seeds)):
        one = replace(cfg, fast_weight=weight)
        print(f"[{k + 1}/{total}] {run_label(scheduler, weight, cfg.depth)} seed={seed} ...", flush=True)
        record = run_live(one, scheduler, seed, work)
        profile = LatencyProfile("measured", tuple(record["latency_profile_ms"]))
        record["sim_ideal"] = simulate_same(one, scheduler, seed, profile=profile)
        record["sim"] = simulate_same(one, scheduler, seed, record["batch_overhead_ms"], profile)
        runs.append(record)
        if record["saturated"]:
            print(
                f"  warning: the machine was {record['machine_busy_pct']:.0f}% busy: this run measures the machine, not the scheduler",
                flush=True,
            )
    print(table(runs))
    if cfg.output:
        Path(cfg.output).parent.mkdir(parents=True, exist_ok=True)
        command = "lerobot-armory-bench " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        Path(cfg.output).write_text(json.dumps({"command": command, "runs": runs}, indent=2) + "\n")
        print(f"wrote {cfg.output}")
    return runs


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(BenchConfig, argv, "lerobot-armory-bench")
    run_or_exit(run, cfg, "lerobot-armory-bench")


if __name__ == "__main__":
    main()

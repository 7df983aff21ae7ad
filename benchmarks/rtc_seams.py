"""Real-time chunking from the mirror: seam jumps with and without RTC, live, with π0.5.

Serves the π0.5 demo policy (LeRobot's PI05 classes at the tiny size, random weights; CPU) to
armory_sim robots through the real server and clients, at the presets' timing (emulated GPU
latency, EDF), once with ``--rtc.enabled=false`` and once with ``--rtc.enabled=true``, and reads
each robot's own seam measurement (``robot/actions.py``: ‖a_new(i) − a_old(i)‖ at every switch).

1. Fleet sizes N = 1, 4, 10 (libero half-fast) and N = 4 on piper timing: mean seam with RTC
   over mean seam without; target ≤ 0.2 for every row.
2. Network jitter: N = 4, one-way delay log-normal with a 10 ms median and σ = 0 … 1.5.
   Each guided chunk's predicted delay (the batch log) is paired with the offset the robot
   really switched at (its seam log): the prediction's error, and the seam by error.
3. A wrong delay prediction, controlled: one guided chunk per trial, its true switch index
   fixed and the delay given to RTC off by e = −3 … +3 steps (engine only, no network).
4. RTC's latency cost per batch size b = 1..10 (guided over plain forward pass, this machine).

Writes ``docs/results/rtc/README.md`` and ``results.json``; exits 1 if a target is missed.

    .venv/bin/python benchmarks/rtc_seams.py [--duration_s=15] [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

from lerobot_armory.bench.live import BenchConfig, run_live  # noqa: E402
from lerobot_armory.sim.presets import get_preset  # noqa: E402

OUT = Path("docs/results/rtc")
TARGET_RATIO = 0.2
SIGMAS = (0.0, 0.5, 1.0, 1.5)
ERRORS = (-3, -2, -1, 0, 1, 2, 3)


def policy_for(chunk_size: int) -> str:
    """The tiny π0.5 demo for this chunk size (built once, offline)."""
    path = Path("out") / f"pi05-tiny-H{chunk_size}"
    if not (path / "config.json").is_file():
        from lerobot_armory.demo.pi05 import make_pi05_policy

        make_pi05_policy(path, size="tiny", chunk_size=chunk_size)
    return str(path)


def live(
    preset: str, robots: int, rtc: bool, duration: float, median_ms: float = 0.0, sigma: float = 0.0, planner: bool = False, seed: int = 0,
    rtc_args: str = "",
) -> dict[str, Any]:
    """One live run (π0.5, or the analytic planner); returns seams, jerk and successes per tier
    and the delay-prediction pairs."""
    chunk = get_preset(preset).chunk_size
    cfg = BenchConfig(
        preset=preset, mix="half-fast", robots=robots, schedulers="edf", duration_s=duration,
        policy_path=None if planner else policy_for(chunk), policy_args=f"--rtc.enabled={str(rtc).lower()} {rtc_args}".strip(),
        net_median_ms=median_ms, net_sigma=sigma, groups=min(2, robots),
    )  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        record = run_live(cfg, "edf", seed, work)
        batches = [json.loads(line) for p in work.glob("*/batches.jsonl") for line in p.read_text().splitlines() if line.strip()]
    predicted = {}
    for b in batches:
        for robot, i_start, delay in zip(b["robots"], b["i_starts"], b.get("rtc_delays") or [None] * len(b["robots"]), strict=True):
            if delay is not None:
                predicted[(robot, i_start)] = delay
    pairs = []  # (error in steps, jump)
    jumps = []
    for r in record["per_robot"]:
        for i_start, offset, jump in r.get("seam_log", []):
            jumps.append(jump)
            if (r["robot_id"], i_start) in predicted:
                pairs.append((offset - predicted[(r["robot_id"], i_start)], jump))
    tiers = {t: v.get("seam_jump_mean") for t, v in record["tiers"].items()}
    jerk = [r["action_jerk_mean"] for r in record["per_robot"] if r.get("action_jerk_mean") is not None]
    return {
        "preset": preset, "robots": robots, "rtc": rtc, "policy": "armory_planner" if planner else "pi05-tiny", "seed": seed, "policy": "armory_planner" if planner else "pi05-tiny", "seed": seed, "net_median_ms": median_ms, "net_sigma": sigma,
        "seam_mean": float(np.mean(jumps)) if jumps else None, "seams": len(jumps), "seam_by_tier": tiers,
        "action_jerk_mean": float(np.mean(jerk)) if jerk else None,
        "switches_after_gap": sum(r.get("switches_after_gap", 0) for r in record["per_robot"]),
        "starvation_pct": {t: v["starvation_pct"] for t, v in record["tiers"].items()},
        "successes_per_min": {t: v["successes_per_min"] for t, v in record["tiers"].items()},
        "delay_errors": pairs,
    }  # fmt: skip


def wrong_delay_sweep(trials: int) -> dict[int, dict[str, float]]:
    """Seam at a fixed true switch index when RTC is told the delay off by ``e`` steps."""
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions
    from lerobot_armory.engine.rtc import Prefix
    from lerobot_armory.engine.options import RTCOptions

    engine = PolicyEngine(PolicyOptions(policy_for(10), "cpu"), RTCOptions(enabled=True, delay_margin=0))  # the delay as told
    shift, true_delay = 2, 3  # the new observation is 2 steps into the old chunk; it arrives 3 steps later
    out: dict[int, list[float]] = {e: [] for e in (None, *ERRORS)}  # None: unguided
    for t in range(trials):
        old_obs, new_obs = engine.example_observation(2 * t), engine.example_observation(2 * t + 1)
        old, old_model = engine.infer_guided([old_obs], ["task"], [t], [None])
        switch = shift + true_delay
        plain = engine.infer([new_obs], ["task"], [10_000 + t])
        out[None].append(float(np.linalg.norm(plain[0, true_delay] - old[0, switch])))
        for e in ERRORS:
            prefix = Prefix(old_model[0, shift:], max(0, true_delay + e))
            new, _ = engine.infer_guided([new_obs], ["task"], [10_000 + t], [prefix])
            out[e].append(float(np.linalg.norm(new[0, true_delay] - old[0, switch])))
    base = statistics.mean(out[None])
    return {e: {"seam_mean": statistics.mean(v), "ratio_to_unguided": statistics.mean(v) / base} for e, v in out.items() if e is not None} | {
        "unguided_seam_mean": base  # type: ignore[dict-item]
    }


def latency_cost(max_b: int, reps: int) -> list[dict[str, float]]:
    """Median forward pass, plain and guided, for b = 1..max_b (one engine, same process)."""
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions
    from lerobot_armory.engine.options import RTCOptions

    engine = PolicyEngine(PolicyOptions(policy_for(10), "cpu"), RTCOptions(enabled=True))
    engine.warmup(max_b, log_progress=False)
    rows = []
    for b in range(1, max_b + 1):
        obs = [engine.example_observation(k) for k in range(b)]
        prefixes = engine.example_prefixes(b)
        plain, guided = [], []
        for _ in range(reps):  # interleaved, so drift on this noisy machine hits both alike
            t0 = time.perf_counter()
            engine.infer(obs, ["task"] * b)
            t1 = time.perf_counter()
            engine.infer_guided(obs, ["task"] * b, None, prefixes)
            guided.append(time.perf_counter() - t1)
            plain.append(t1 - t0)
        p, g = 1000 * statistics.median(plain), 1000 * statistics.median(guided)
        rows.append({"b": b, "plain_ms": p, "guided_ms": g, "extra_ms": g - p, "ratio": g / p})
    return rows


def _fmt(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _ratio(on: dict[str, Any], off: dict[str, Any]) -> float:
    return on["seam_mean"] / off["seam_mean"]


def part_fleets(args: argparse.Namespace, targets: Targets) -> tuple[list[str], Any]:
    fleets = [("libero", 4)] if args.quick else [("libero", 1), ("libero", 4), ("libero", 10), ("piper", 4)]
    runs = []
    lines = ["## Seam jump with and without RTC (π0.5 tiny, EDF, emulated l40s-pi05 latency, no network delay)", ""]
    lines += [
        "| preset | N | seam without | seam with RTC | ratio | fast / slow with RTC | action jerk without / with | switches after a gap (off / on) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for preset, n in fleets:
        pair = []
        for rtc in (False, True):
            print(f"[{preset} N={n} rtc={rtc}] ...", flush=True)
            pair.append(live(preset, n, rtc, args.duration_s))
        runs += pair
        off, on = pair
        tiers = " / ".join(_fmt(on["seam_by_tier"].get(t)) for t in ("fast", "slow"))
        lines.append(
            f"| {preset} | {n} | {_fmt(off['seam_mean'])} | {_fmt(on['seam_mean'])} | {_ratio(on, off):.3f} | {tiers} | "
            f"{_fmt(off['action_jerk_mean'])} / {_fmt(on['action_jerk_mean'])} | {off['switches_after_gap']} / {on['switches_after_gap']} |"
        )
        targets.check(f"seam ratio {preset} N={n}", _ratio(on, off), TARGET_RATIO, "x")
    return lines, runs


def part_jitter(args: argparse.Namespace, targets: Targets) -> tuple[list[str], Any]:
    runs = []
    lines = ["## Network jitter (π0.5 tiny, libero half-fast, N = 4, one-way delay log-normal, median 10 ms)", ""]
    lines += [
        "| σ | seam without | seam with RTC | ratio | delay prediction exact | within ±1 step | mean seam when exact / off by 1 / off by ≥ 2 |",
        "|---|---|---|---|---|---|---|",
    ]
    for sigma in SIGMAS:
        pair = []
        for rtc in (False, True):
            print(f"[jitter σ={sigma} rtc={rtc}] ...", flush=True)
            pair.append(live("libero", 4, rtc, args.duration_s, 10.0, sigma))
        runs += pair
        off, on = pair
        errs = on["delay_errors"]
        by = {name: [j for e, j in errs if test(e)] for name, test in (("0", lambda e: e == 0), ("1", lambda e: abs(e) == 1), ("2+", lambda e: abs(e) >= 2))}
        share = {k: 100.0 * len(v) / max(1, len(errs)) for k, v in by.items()}
        means = " / ".join(_fmt(float(np.mean(v)) if v else None) for v in by.values())
        lines.append(
            f"| {sigma:g} | {_fmt(off['seam_mean'])} | {_fmt(on['seam_mean'])} | {_ratio(on, off):.3f} | {share['0']:.0f} % | "
            f"{share['0'] + share['1']:.0f} % | {means} |"
        )
    for r in runs:
        r["delay_errors"] = [[e, j] for e, j in r["delay_errors"]]
    return lines, runs


def part_wrong(args: argparse.Namespace, targets: Targets) -> tuple[list[str], Any]:
    print("[wrong delay sweep] ...", flush=True)
    sweep = wrong_delay_sweep(10 if args.quick else 40)
    lines = ["## A wrong delay prediction (π0.5 tiny, engine only: true switch 3 steps after the observation, RTC told 3 + e)", ""]
    lines += [f"Unguided seam: {sweep['unguided_seam_mean']:.3f}.", "", "| e (steps) | seam | ratio to unguided |", "|---|---|---|"]
    lines += [f"| {e:+d} | {sweep[e]['seam_mean']:.3f} | {sweep[e]['ratio_to_unguided']:.3f} |" for e in ERRORS]
    return lines, {str(k): v for k, v in sweep.items()}


def part_cost(args: argparse.Namespace, targets: Targets) -> tuple[list[str], Any]:
    print("[latency cost] ...", flush=True)
    cost = latency_cost(10, 5 if args.quick else 15)
    lines = ["## RTC's latency cost per batch size (π0.5 tiny, CPU of this machine, median forward pass)", ""]
    lines += ["| b | plain ms | guided ms | extra ms | ratio |", "|---|---|---|---|---|"]
    lines += [f"| {r['b']} | {r['plain_ms']:.1f} | {r['guided_ms']:.1f} | {r['extra_ms']:.1f} | {r['ratio']:.2f} |" for r in cost]
    return lines, cost


def part_planner(args: argparse.Namespace, targets: Targets) -> tuple[list[str], Any]:
    """The analytic planner (which solves armory_sim's tasks) with its leftover contract: the
    effect of RTC on the dynamic task's successes, with network jitter."""
    runs = []
    seeds = 1 if args.quick else 3
    lines = ["## The analytic planner on the dynamic task (libero half-fast, N = 4, EDF, 10 ms median one-way delay, σ = 0.5)", ""]
    lines += ["| RTC | fast successes/min | fast starvation % | seam fast / slow | action jerk |", "|---|---|---|---|---|"]
    variants = [(False, "", "off"), (True, "", "on, horizon 10 (LeRobot's default)"), (True, "--rtc.execution_horizon=5", "on, horizon 5")]
    for rtc, extra, label in variants:
        rows = []
        for seed in range(seeds):
            print(f"[planner {label} seed={seed}] ...", flush=True)
            rows.append(live("libero", 4, rtc, args.duration_s, 10.0, 0.5, planner=True, seed=seed, rtc_args=extra))
        runs += rows
        succ = [r["successes_per_min"]["fast"] for r in rows]
        starv = [r["starvation_pct"]["fast"] for r in rows]
        fast = [r["seam_by_tier"].get("fast") for r in rows if r["seam_by_tier"].get("fast") is not None]
        slow = [r["seam_by_tier"].get("slow") for r in rows if r["seam_by_tier"].get("slow") is not None]
        jerk = [r["action_jerk_mean"] for r in rows if r["action_jerk_mean"] is not None]
        spread = f" (seeds: {', '.join(f'{x:.1f}' for x in succ)})" if len(succ) > 1 else ""
        lines.append(
            f"| {label} | {np.mean(succ):.1f}{spread} | {np.mean(starv):.1f} | "
            f"{_fmt(float(np.mean(fast)) if fast else None)} / {_fmt(float(np.mean(slow)) if slow else None)} | {_fmt(float(np.mean(jerk)) if jerk else None)} |"
        )
    return lines, runs


PARTS = {"fleets": part_fleets, "jitter": part_jitter, "wrong": part_wrong, "cost": part_cost, "planner": part_planner}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration_s", type=float, default=15.0)
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated parts to run: {', '.join(PARTS)}")
    parser.add_argument("--quick", action="store_true", help="short smoke run, nothing written")
    args = parser.parse_args()
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        parser.error(f"unknown part(s) {', '.join(unknown)}; choose from {', '.join(PARTS)}")
    OUT.mkdir(parents=True, exist_ok=True)
    targets = Targets()
    results_file = OUT / "results.json"
    saved = json.loads(results_file.read_text()) if results_file.is_file() and not args.quick else {}
    for name in parts:
        lines, data = PARTS[name](args, targets)
        print("\n".join(lines) + "\n", flush=True)
        saved[name] = {"lines": lines, "data": data, "duration_s": args.duration_s, "when": time.strftime("%Y-%m-%d %H:%M")}
    if not args.quick:
        results_file.write_text(json.dumps(saved, indent=1))
        text = "\n\n".join("\n".join(saved[p]["lines"]) for p in PARTS if p in saved)
        (OUT / "tables.md").write_text(text + "\n")
    targets.finish()


if __name__ == "__main__":
    main()

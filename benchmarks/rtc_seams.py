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
        from lerobot_armory.server.demo_pi05 import make_pi05_policy

        make_pi05_policy(path, size="tiny", chunk_size=chunk_size)
    return str(path)


def live(preset: str, robots: int, rtc: bool, duration: float, median_ms: float = 0.0, sigma: float = 0.0) -> dict[str, Any]:
    """One live run; returns seams per tier and the delay-prediction pairs."""
    chunk = get_preset(preset).chunk_size
    cfg = BenchConfig(
        preset=preset, mix="half-fast", robots=robots, schedulers="edf", duration_s=duration, policy_path=policy_for(chunk),
        policy_args=f"--rtc.enabled={str(rtc).lower()}", net_median_ms=median_ms, net_sigma=sigma,
        groups=min(2, robots),
    )  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        record = run_live(cfg, "edf", 0, work)
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
    return {
        "preset": preset, "robots": robots, "rtc": rtc, "net_median_ms": median_ms, "net_sigma": sigma,
        "seam_mean": float(np.mean(jumps)) if jumps else None, "seams": len(jumps), "seam_by_tier": tiers,
        "switches_after_gap": sum(r.get("switches_after_gap", 0) for r in record["per_robot"]),
        "starvation_pct": {t: v["starvation_pct"] for t, v in record["tiers"].items()},
        "successes_per_min": {t: v["successes_per_min"] for t, v in record["tiers"].items()},
        "delay_errors": pairs,
    }  # fmt: skip


def wrong_delay_sweep(trials: int) -> dict[int, dict[str, float]]:
    """Seam at a fixed true switch index when RTC is told the delay off by ``e`` steps."""
    from lerobot_armory.server.engine import PolicyEngine, PolicyOptions
    from lerobot_armory.server.rtc import Prefix, RTCOptions

    engine = PolicyEngine(PolicyOptions(policy_for(10), "cpu"), RTCOptions(enabled=True))
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
    from lerobot_armory.server.engine import PolicyEngine, PolicyOptions
    from lerobot_armory.server.rtc import RTCOptions

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration_s", type=float, default=15.0)
    parser.add_argument("--quick", action="store_true", help="N = 4 only, no jitter sweep (a smoke run)")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    targets = Targets()
    fleets = [("libero", 4)] if args.quick else [("libero", 1), ("libero", 4), ("libero", 10), ("piper", 4)]
    runs: list[dict[str, Any]] = []
    lines = ["## Seam jump with and without RTC (EDF, emulated l40s-pi05 latency, no network delay)", ""]
    lines += ["| preset | N | seam without | seam with RTC | ratio | fast / slow with RTC | switches after a gap (off / on) |", "|---|---|---|---|---|---|---|"]
    for preset, n in fleets:
        pair = []
        for rtc in (False, True):
            print(f"[{preset} N={n} rtc={rtc}] ...", flush=True)
            pair.append(live(preset, n, rtc, args.duration_s))
        runs += pair
        off, on = pair
        ratio = on["seam_mean"] / off["seam_mean"]
        tiers = " / ".join(_fmt(on["seam_by_tier"].get(t)) for t in ("fast", "slow"))
        lines.append(
            f"| {preset} | {n} | {_fmt(off['seam_mean'])} | {_fmt(on['seam_mean'])} | {ratio:.3f} | {tiers} | {off['switches_after_gap']} / {on['switches_after_gap']} |"
        )
        targets.check(f"seam ratio {preset} N={n}", ratio, TARGET_RATIO, "x")
    if not args.quick:
        lines += ["", "## Network jitter (libero half-fast, N = 4, one-way delay log-normal, median 10 ms)", ""]
        lines += ["| σ | seam without | seam with RTC | ratio | delay prediction exact | within ±1 step | mean seam when exact / off by 1 / off by ≥ 2 |", "|---|---|---|---|---|---|---|"]
        for sigma in SIGMAS:
            pair = []
            for rtc in (False, True):
                print(f"[jitter σ={sigma} rtc={rtc}] ...", flush=True)
                pair.append(live("libero", 4, rtc, args.duration_s, 10.0, sigma))
            runs += pair
            off, on = pair
            errs = on["delay_errors"]
            exact = [j for e, j in errs if e == 0]
            one = [j for e, j in errs if abs(e) == 1]
            more = [j for e, j in errs if abs(e) >= 2]
            share = (lambda xs: 100.0 * len(xs) / len(errs)) if errs else (lambda xs: 0.0)
            lines.append(
                f"| {sigma:g} | {_fmt(off['seam_mean'])} | {_fmt(on['seam_mean'])} | {on['seam_mean'] / off['seam_mean']:.3f} | "
                f"{share(exact):.0f} % | {share(exact) + share(one):.0f} % | "
                f"{_fmt(np.mean(exact) if exact else None)} / {_fmt(np.mean(one) if one else None)} / {_fmt(np.mean(more) if more else None)} |"
            )
    print("[wrong delay sweep] ...", flush=True)
    sweep = wrong_delay_sweep(10 if args.quick else 40)
    lines += ["", "## A wrong delay prediction (engine only: true switch 3 steps after the observation, RTC told 3 + e)", ""]
    lines += [f"Unguided seam: {sweep['unguided_seam_mean']:.3f}.", "", "| e (steps) | seam | ratio to unguided |", "|---|---|---|"]
    for e in ERRORS:
        lines.append(f"| {e:+d} | {sweep[e]['seam_mean']:.3f} | {sweep[e]['ratio_to_unguided']:.3f} |")
    print("[latency cost] ...", flush=True)
    cost = latency_cost(10, 5 if args.quick else 15)
    lines += ["", "## RTC's latency cost per batch size (tiny π0.5, CPU of this machine, median forward pass)", ""]
    lines += ["| b | plain ms | guided ms | extra ms | ratio |", "|---|---|---|---|---|"]
    lines += [f"| {r['b']} | {r['plain_ms']:.1f} | {r['guided_ms']:.1f} | {r['extra_ms']:.1f} | {r['ratio']:.2f} |" for r in cost]
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.quick:
        for r in runs:
            r["delay_errors"] = [[e, j] for e, j in r["delay_errors"]]
        (OUT / "results.json").write_text(json.dumps({"runs": runs, "wrong_delay": {str(k): v for k, v in sweep.items()}, "latency": cost}, indent=1))
        (OUT / "tables.md").write_text(text)
    targets.finish()


if __name__ == "__main__":
    main()

"""Dispatch timing (``--scheduler.wait_ms``) in the simulator, with jitter and prediction error.

The offline study (``research/benchmarks/true_optimum.py``) shows that the best deterministic
schedules idle on purpose. Whether waiting pays on a real network is a different question: the
deterministic gain sits on a knife edge (libero: a batch of 3 plus the network takes 149.9 ms
against a 150 ms tick). This benchmark measures it where it matters, in the simulator with the
presets' log-normal network jitter, the robots' random tick phases and clock offsets, and with
the scheduler's predictions deliberately wrong:

- ``nominal``: the scheduler's latency table is the truth;
- ``latency +1 ms`` / ``latency -1 ms``: every batch really takes 1 ms longer / shorter than
  the table the scheduler plans with;
- ``jitter x2``: the network's log-normal σ doubled (the mirror's arrival predictions err more).

Each pair (EDF against EDF +wait, Rollout against Rollout +wait) runs on the same seeds (same
network draws and phases); Δ = with timing − without, executed robot time in % (every robot
weighs 1) and fast-tier starvation in points, mean ± 95 % half-width over the seeds. Scored
after a warm-up (steady state; nothing is told an end).

Targets (exit 1 on a miss), fixed before the evaluation seeds (100 ..) were run (the rule and
its 10 ms / 2 ms knobs were chosen on seeds 0 .. 11):

- Rollout +wait never loses significantly to Rollout (no fleet × condition whose interval of
  Δ executed lies below zero);
- EDF +wait never loses significantly to EDF in the nominal condition.

Run: ``.venv/bin/python benchmarks/dispatch_timing.py [--seeds=16] [--duration_s=60] [--out=docs/results/timing/sim.md]``
(about 10-15 minutes on 2 cores; ``--quick`` for a smoke test).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

from lerobot_armory.network_delay import LogNormalDelay  # noqa: E402
from lerobot_armory.inference_latency import LatencyProfile, load_profile  # noqa: E402
from lerobot_armory.schedulers import make_scheduler_config  # noqa: E402
from lerobot_armory.sim.presets import fleet_specs, get_preset  # noqa: E402
from lerobot_armory.sim.simulator import FleetSimulator  # noqa: E402

WAIT_MS, MARGIN_MS = 10.0, 2.0
FLEETS = [
    (p, m, n)
    for p in ("libero", "piper")
    for m, n in (("all-fast", 3), ("all-fast", 5), ("half-fast", 4), ("half-fast", 6), ("one-fast", 10), ("half-fast", 10))
]
# (label, latency error ms, network sigma factor)
CONDITIONS = [("nominal", 0.0, 1.0), ("latency +1 ms", 1.0, 1.0), ("latency -1 ms", -1.0, 1.0), ("jitter x2", 0.0, 2.0)]
PAIRS = [("EDF", "edf"), ("Rollout", "rollout")]


def run_one(job: tuple) -> tuple[float, float, float]:
    """(executed robot-s, fast-tier starvation %, held s) of one simulated run."""
    preset_name, mix, n, scheduler, wait_ms, latency_err_ms, sigma_factor, seed, duration, warmup = job
    preset = get_preset(preset_name)
    profile = load_profile(preset.latency_profile)
    cap = preset.default_batch_cap(mix)
    options = {"wait_ms": wait_ms, "wait_margin_ms": MARGIN_MS} if wait_ms > 0 else {}
    sched = make_scheduler_config(scheduler, **options).make(profile, cap)
    true = None
    if latency_err_ms:
        true = LatencyProfile(f"{profile.name}{latency_err_ms:+g}ms", tuple(v + latency_err_ms for v in profile.latency_ms), profile.device)
    net = LogNormalDelay(preset.net_median_ms / 1000.0, preset.net_sigma * sigma_factor)
    specs = fleet_specs(preset, mix, n)
    res = FleetSimulator(specs, sched, duration, net, net, seed, true_latency=true, warmup_s=warmup).run()
    fast = res.tier_starvation_pct("fast") if res.tier("fast") else float("nan")
    return res.executed_s, fast, res.held_s


def interval(d: np.ndarray) -> tuple[float, float]:
    return float(d.mean()), (1.96 * float(d.std(ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else float("nan"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--first_seed", type=int, default=100, help="evaluation seeds (the knobs were chosen on 0 .. 11)")
    ap.add_argument("--duration_s", type=float, default=60.0)
    ap.add_argument("--warmup_s", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 fleets, 3 seeds, 20 s: a smoke test")
    ap.add_argument("--out", help="also write the table (markdown) here")
    args = ap.parse_args()
    fleets, conditions = FLEETS, CONDITIONS
    if args.quick:
        fleets, conditions, args.seeds, args.duration_s, args.warmup_s = FLEETS[:1] + FLEETS[6:7], CONDITIONS[:2], 3, 20.0, 5.0
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    lines = [
        "# Dispatch timing in the simulator: with against without `--scheduler.wait_ms`",
        "",
        f"Wait ≤ {WAIT_MS:g} ms, margin {MARGIN_MS:g} ms. Paired seeds {seeds.start}..{seeds.stop - 1}, {args.duration_s:g} s each, "
        f"the first {args.warmup_s:g} s not scored; the presets' network (log-normal, median 3.75 ms) and latency table "
        "(l40s-pi05). Δ = with timing − without: executed robot time in % (all robots weigh 1), fast-tier starvation in "
        "points (negative is better); mean ± 95 % half-width. 'held' = device time spent waiting on purpose.",
        "",
        f"Command: `.venv/bin/python benchmarks/dispatch_timing.py --seeds={args.seeds} --duration_s={args.duration_s:g}`",
        "",
        "| fleet | condition | pair | Δ executed % | Δ fast starvation pp | held % of time | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    losses: dict[str, list[str]] = {"Rollout": [], "EDF": []}
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for preset, mix, n in fleets:
            for cond, lat, sig in conditions:
                for pair, name in PAIRS:
                    jobs = [(preset, mix, n, name, w, lat, sig, s, args.duration_s, args.warmup_s) for w in (0.0, WAIT_MS) for s in seeds]
                    out = np.array(list(pool.map(run_one, jobs)))
                    base, timed = out[: len(seeds)], out[len(seeds) :]
                    d_exec, h_exec = interval(100.0 * (timed[:, 0] - base[:, 0]) / base[:, 0])
                    d_fast, h_fast = (interval(timed[:, 1] - base[:, 1])) if not np.isnan(base[:, 1]).any() else (float("nan"), float("nan"))
                    held = 100.0 * float(timed[:, 2].mean()) / args.duration_s
                    if d_exec - h_exec > 0:
                        verdict = "timing wins"
                    elif d_exec + h_exec < 0:
                        verdict = "timing loses"
                        if pair == "Rollout" or cond == "nominal":
                            losses[pair].append(f"{preset} {mix} N={n} {cond}")
                    else:
                        verdict = "tie"
                    fleet = f"{preset} {mix} N={n}"
                    lines.append(
                        f"| {fleet} | {cond} | {pair} | {d_exec:+.2f} ± {h_exec:.2f} | {d_fast:+.2f} ± {h_fast:.2f} | {held:.2f} | {verdict} |"
                    )
                    print(f"[{time.perf_counter() - started:6.0f} s] {fleet}, {cond}, {pair}: Δ executed {d_exec:+.2f} ± {h_exec:.2f} %, "
                          f"Δ fast {d_fast:+.2f} ± {h_fast:.2f} pp, held {held:.2f} % -> {verdict}", flush=True)  # fmt: skip
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    targets = Targets()
    for pair in ("Rollout", "EDF"):
        for where in losses[pair]:
            print(f"  {pair} +wait loses significantly: {where}")
    targets.check("fleet x condition where Rollout +wait loses significantly to Rollout", len(losses["Rollout"]), 0, "")
    targets.check("fleet where EDF +wait loses significantly to EDF (nominal)", len(losses["EDF"]), 0, "")
    targets.finish()


if __name__ == "__main__":
    main()

"""Reference experiments, live (docs/spec.md §5 / issue "Live fleet benchmark"): the real server with the
``l40s-pi05`` profile emulated, ``armory_sim`` fleets with ``libero`` timing, RR / EDF / LA w=1,3,5,
per-tier starvation and successes per minute beside the simulator's prediction.

    .venv/bin/python benchmarks/live_reference.py --sizes=4,10 --mixes=one-fast,half-fast \\
        --duration_s=30 --seeds=1 --out_dir=docs/results/live

Writes ``live.csv``, ``live.json``, ``COMMAND.md`` and figures (stacked per-tier throughput bars per
scheduler, starvation vs fleet size, live vs simulated starvation) and prints the tables. Exits 1
if a run saturated the machine or live and simulated starvation differ by more than 3 points.
"""

from __future__ import annotations

import csv
import json
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import draccus

from lerobot_armory.bench.live import BenchConfig, run, table

SCHEDULERS = "rr,edf,lookahead@1,lookahead@3,lookahead@5"
FIDELITY_PP = 3.0


@dataclass
class LiveReferenceConfig:
    sizes: str = "4,10"
    mixes: str = "one-fast,half-fast"
    duration_s: float = 30.0
    seeds: int = 1
    preset: str = "libero"
    emulate_profile: str = "l40s-pi05"
    out_dir: str = "docs/results/live"


def main() -> None:
    cfg = draccus.parse(LiveReferenceConfig, args=sys.argv[1:])
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for mix in cfg.mixes.split(","):
        for n in (int(x) for x in cfg.sizes.split(",")):
            bench = BenchConfig(
                preset=cfg.preset, mix=mix, robots=n, schedulers=SCHEDULERS, emulate_profile=cfg.emulate_profile,
                duration_s=cfg.duration_s, seeds=cfg.seeds, groups=2 if n <= 4 else 3,
            )  # fmt: skip
            runs += run(bench)
    command = "python benchmarks/live_reference.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    (out / "live.json").write_text(json.dumps({"command": command, "runs": runs}, indent=1) + "\n")
    fields = ["preset", "mix", "robots", "label", "seed", "max_batch_size", "latency_profile", "duration_s", "cpu_busy_pct",
              "batch_overhead_ms", "fast_starvation_pct", "fast_sim_starvation_pct", "fast_sim_ideal_starvation_pct",
              "slow_starvation_pct", "slow_sim_starvation_pct", "slow_sim_ideal_starvation_pct",
              "fast_successes_per_min", "slow_successes_per_min", "mean_batch_size"]  # fmt: skip
    with open(out / "live.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in runs:
            sizes = {int(k): v for k, v in r["batch_sizes"].items()}
            row = {k: r.get(k, "") for k in fields}
            for tier in ("fast", "slow"):
                t = r["tiers"].get(tier)
                row[f"{tier}_starvation_pct"] = "" if t is None else round(t["starvation_pct"], 2)
                row[f"{tier}_successes_per_min"] = "" if t is None else round(t["successes_per_min"], 2)
                sim = r["sim"].get(tier)
                row[f"{tier}_sim_starvation_pct"] = "" if sim is None else round(sim, 2)
                ideal = r.get("sim_ideal", {}).get(tier)
                row[f"{tier}_sim_ideal_starvation_pct"] = "" if ideal is None else round(ideal, 2)
            row["mean_batch_size"] = round(sum(k * v for k, v in sizes.items()) / max(1, sum(sizes.values())), 3)
            w.writerow(row)
    from lerobot_armory.bench.live_plots import plot_live

    figures = plot_live(runs, out)
    text = "\n\n".join(
        f"== {mix}, N={n} ==\n" + table([r for r in runs if r["mix"] == mix and r["robots"] == n])
        for mix in cfg.mixes.split(",") for n in (int(x) for x in cfg.sizes.split(","))
    )  # fmt: skip
    (out / "summary.txt").write_text(text + "\n")
    (out / "COMMAND.md").write_text(f"# How these results were made\n\n```\n{command}\n```\n")
    print(text)
    print("figures:", ", ".join(str(p) for p in figures))
    bad = []
    for r in runs:
        if r["saturated"]:
            bad.append(f"{r['mix']} N={r['robots']} {r['label']}: machine saturated ({r['machine_busy_pct']:.0f}% busy; other processes were running)")
        for tier, t in r["tiers"].items():
            gap = abs(t["starvation_pct"] - r["sim"][tier])
            if gap > FIDELITY_PP:
                bad.append(f"{r['mix']} N={r['robots']} {r['label']} {tier}: live {t['starvation_pct']:.1f}% vs sim {r['sim'][tier]:.1f}%")
    if bad:
        print("MISS:\n  " + "\n  ".join(bad))
        sys.exit(1)
    print(f"all live runs within {FIDELITY_PP} points of the simulator, none saturated")


if __name__ == "__main__":
    main()

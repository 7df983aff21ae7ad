"""Success vs forced extra delay: the demo policy solves both armory_sim tasks when served on
time, and the dynamic task's success falls as chunks go stale.

Two robots (one fast on the dynamic scene, one slow on the static scene, libero timing) share a
real server with no contention (emulated l40s-pi05 latency); an extra one-way network delay is
forced on every message (client-side emulation, σ = 0). Prints successes per minute per task for
each delay, writes ``docs/results/live/staleness.csv`` and ``staleness.png``, and exits 1 unless
the fresh success rates are high and the dynamic task degrades with delay.

    .venv/bin/python benchmarks/staleness_curve.py [--duration_s=20]
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

from lerobot_armory.bench.live import BenchConfig, run  # noqa: E402

DELAYS_MS = (0.0, 50.0, 100.0, 200.0, 400.0)


def main() -> None:
    duration = float(sys.argv[1].split("=")[1]) if len(sys.argv) > 1 else 20.0
    out = Path("docs/results/live")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for delay in DELAYS_MS:
        r = run(BenchConfig(robots=2, mix="one-fast", schedulers="edf", duration_s=duration, net_median_ms=delay, groups=1))[0]
        rows.append(
            {
                "extra_one_way_delay_ms": delay,
                "dynamic_successes_per_min": round(r["tiers"]["fast"]["successes_per_min"], 2),
                "static_successes_per_min": round(r["tiers"]["slow"]["successes_per_min"], 2),
                "dynamic_starvation_pct": round(r["tiers"]["fast"]["starvation_pct"], 2),
                "static_starvation_pct": round(r["tiers"]["slow"]["starvation_pct"], 2),
            }
        )
    with open(out / "staleness.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    xs = [r["extra_one_way_delay_ms"] for r in rows]
    ax.plot(xs, [r["dynamic_successes_per_min"] for r in rows], marker="o", color="tab:red", label="dynamic (intercept moving target)")
    ax.plot(xs, [r["static_successes_per_min"] for r in rows], marker="o", color="tab:blue", label="static (reach fixed target)")
    ax.set_xlabel("forced extra one-way delay (ms), each direction")
    ax.set_ylabel("successes per minute")
    ax.set_title("armory_planner served live: success vs chunk staleness")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "staleness.png", dpi=110)
    print(f"{'delay ms':>8} {'dynamic succ/min':>16} {'static succ/min':>15} {'dyn starv%':>10} {'static starv%':>13}")
    for r in rows:
        print(
            f"{r['extra_one_way_delay_ms']:>8g} {r['dynamic_successes_per_min']:>16.1f} {r['static_successes_per_min']:>15.1f} "
            f"{r['dynamic_starvation_pct']:>10.1f} {r['static_starvation_pct']:>13.1f}"
        )
    t = Targets()
    fresh = rows[0]
    t.check_min("fresh dynamic successes/min", fresh["dynamic_successes_per_min"], 30)
    t.check_min("fresh static successes/min", fresh["static_successes_per_min"], 30)
    t.check("dynamic success at 400 ms / fresh", rows[-1]["dynamic_successes_per_min"] / max(1e-9, fresh["dynamic_successes_per_min"]), 0.7, "")
    t.finish()


if __name__ == "__main__":
    main()

"""Figures of the live benchmark."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lerobot_armory.robot_spec import TIERS  # noqa: E402
from lerobot_armory.sim.sweep_plots import LABEL_ORDER  # noqa: E402


def plot_live(runs: list[dict[str, Any]], out: Path) -> list[Path]:
    """Stacked per-tier throughput bars per scheduler (one panel per mix × N), starvation vs N,
    and live vs simulated starvation."""
    paths = []
    groups = sorted({(r["mix"], r["robots"]) for r in runs})
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.8), squeeze=False)
    for ax, (mix, n) in zip(axes[0], groups, strict=True):
        rows = [r for r in runs if r["mix"] == mix and r["robots"] == n]
        labels = [lab for lab in LABEL_ORDER if any(r["label"] == lab for r in rows)]
        bottom = np.zeros(len(labels))
        for tier, color in (("fast", "tab:red"), ("slow", "tab:blue")):
            vals = np.array([np.mean([r["tiers"][tier]["successes_per_min"] * r["tiers"][tier]["robots"] for r in rows if r["label"] == lab and tier in r["tiers"]] or [0.0]) for lab in labels])
            ax.bar(labels, vals, bottom=bottom, color=color, label=f"{tier} tier")
            bottom += vals
        ax.set_title(f"{mix}, N={n}", fontsize=9)
        ax.set_ylabel("task successes per minute (fleet)")
        ax.tick_params(axis="x", rotation=45, labelsize=8)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"Live throughput per tier ({runs[0]['latency_profile']})")
    fig.tight_layout()
    p = out / "throughput_per_tier.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    mixes = sorted({r["mix"] for r in runs})
    fig, axes = plt.subplots(len(mixes), 2, figsize=(10, 3.3 * len(mixes)), squeeze=False)
    for i, mix in enumerate(mixes):
        for j, tier in enumerate(TIERS):
            ax = axes[i][j]
            for lab in LABEL_ORDER:
                pts = sorted({r["robots"] for r in runs if r["mix"] == mix and r["label"] == lab and tier in r["tiers"]})
                if pts:
                    ys = [np.mean([r["tiers"][tier]["starvation_pct"] for r in runs if r["mix"] == mix and r["label"] == lab and r["robots"] == n]) for n in pts]
                    ax.plot(pts, ys, marker="o", label=lab)
            ax.set_title(f"{mix}: {tier} tier (live)", fontsize=9)
            ax.set_xlabel("fleet size N")
            ax.set_ylabel("starvation %")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    p = out / "starvation_vs_fleet_live.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, ax = plt.subplots(figsize=(5, 5))
    for tier, color in (("fast", "tab:red"), ("slow", "tab:blue")):
        xs = [r["sim"][tier] for r in runs if tier in r["tiers"]]
        ys = [r["tiers"][tier]["starvation_pct"] for r in runs if tier in r["tiers"]]
        ax.scatter(xs, ys, color=color, label=f"{tier} tier", s=18)
    top = max([1.0] + [r["tiers"][t]["starvation_pct"] for r in runs for t in r["tiers"]]) * 1.05
    ax.plot([0, top], [0, top], color="gray", lw=1)
    ax.fill_between([0, top], [-3, top - 3], [3, top + 3], color="gray", alpha=0.15, label="±3 points")
    ax.set_xlabel("simulated starvation %")
    ax.set_ylabel("live starvation %")
    ax.set_title("Mirror fidelity: live vs simulated")
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = out / "live_vs_sim.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths

"""Figures of the reference sweep (matplotlib, headless)."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # headless: no display on servers and CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lerobot_armory.robot_spec import TIERS  # noqa: E402

Record = dict[str, Any]
LABEL_ORDER = ["RR", "EDF", "LA w=1", "LA w=3", "LA w=5"]


def _labels(records: list[Record]) -> list[str]:
    found = {r["label"] for r in records}
    return [lab for lab in LABEL_ORDER if lab in found] + sorted(found - set(LABEL_ORDER))


def _series(records: list[Record], x_key: str, y: Callable[[Record], float | None]) -> dict[str, tuple[list, list, list]]:
    """label -> (xs, means, stds) of ``y`` over seeds, skipping runs where ``y`` is None."""
    acc: dict[str, dict[Any, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        v = y(r)
        if v is not None:
            acc[r["label"]][r[x_key]].append(v)
    out = {}
    for label, by_x in acc.items():
        xs = sorted(by_x)
        out[label] = (xs, [float(np.mean(by_x[x])) for x in xs], [float(np.std(by_x[x])) for x in xs])
    return out


def _tier(tier: str) -> Callable[[Record], float | None]:
    return lambda r: r["tiers"][tier]["starvation_pct"] if tier in r["tiers"] else None


def _plot_lines(ax, records: list[Record], x_key: str, y, title: str, xlabel: str, ylabel: str) -> None:
    series = _series(records, x_key, y)
    for label in _labels(records):
        if label in series:
            xs, means, stds = series[label]
            ax.errorbar(xs, means, yerr=stds, marker="o", ms=3, capsize=2, label=label)
    if not series:
        ax.text(0.5, 0.5, "no robots of this tier", ha="center", va="center", transform=ax.transAxes, color="gray")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)


def plot_fleet(records: list[Record], out: Path) -> list[Path]:
    """Starvation per tier vs fleet size, one line per scheduler; one figure per preset."""
    paths = []
    for preset in sorted({r["preset"] for r in records}):
        rows = [r for r in records if r["preset"] == preset]
        mixes = [m for m in ("all-fast", "one-fast", "half-fast") if any(r["mix"] == m for r in rows)]
        fig, axes = plt.subplots(len(mixes), 2, figsize=(10, 3.2 * len(mixes)), squeeze=False)
        for i, mix in enumerate(mixes):
            sub = [r for r in rows if r["mix"] == mix]
            for k, tier in enumerate(TIERS):
                _plot_lines(axes[i][k], sub, "robots", _tier(tier), f"{preset} {mix}: {tier} tier", "fleet size N", "starvation %")
        axes[0][0].legend(fontsize=8)
        fig.suptitle(f"Starvation per tier vs fleet size ({preset} preset, {rows[0]['latency_profile']})")
        fig.tight_layout()
        path = out / f"starvation_vs_fleet_{preset}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_batch_cap(records: list[Record], out: Path) -> list[Path]:
    """Chosen batch-size histograms per scheduler vs cap, and starvation/throughput vs cap."""
    labels = _labels(records)
    caps = sorted({r["max_batch_size"] for r in records})
    fig, axes = plt.subplots(1, len(labels), figsize=(3.2 * len(labels), 3.4), squeeze=False, sharey=True)
    cmap = plt.get_cmap("viridis")
    top = max(caps)
    for ax, label in zip(axes[0], labels, strict=True):
        counts = np.zeros((len(caps), top))
        for r in records:
            if r["label"] == label:
                for b, c in r["batch_sizes"].items():
                    counts[caps.index(r["max_batch_size"]), int(b) - 1] += c
        frac = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
        bottom = np.zeros(len(caps))
        for b in range(top):
            ax.bar([str(c) for c in caps], frac[:, b], bottom=bottom, color=cmap(b / max(top - 1, 1)), label=f"b={b + 1}")
            bottom += frac[:, b]
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("batch cap")
    axes[0][0].set_ylabel("share of batches")
    axes[0][-1].legend(fontsize=6, ncol=2, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle("Chosen batch sizes vs batch cap (all-fast fleet)")
    fig.tight_layout()
    hist_path = out / "batch_sizes.png"
    fig.savefig(hist_path, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    _plot_lines(axes[0], records, "max_batch_size", lambda r: r["avg_starvation_pct"], "starvation vs cap", "batch cap b", "starvation %")
    _plot_lines(
        axes[1], records, "max_batch_size", lambda r: r["executed_s"] / r["duration_s"],
        "throughput vs cap", "batch cap b", "executed robot-s per s",
    )  # fmt: skip
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    abl_path = out / "batch_cap.png"
    fig.savefig(abl_path, dpi=110)
    plt.close(fig)
    return [hist_path, abl_path]


def plot_network(median_rows: list[Record], sigma_rows: list[Record], out: Path) -> list[Path]:
    """Starvation per tier vs network median (σ = 0) and vs jitter σ (m = 50 ms)."""
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.4), squeeze=False)
    for i, tier in enumerate(TIERS):
        _plot_lines(axes[i][0], median_rows, "net_median_ms", _tier(tier), f"{tier} tier vs median (σ=0)", "one-way median ms", "starvation %")
        _plot_lines(axes[i][1], sigma_rows, "net_sigma", _tier(tier), f"{tier} tier vs jitter (m=50 ms)", "log-normal σ", "starvation %")
    axes[0][0].legend(fontsize=8)
    some = (median_rows or sigma_rows)[0]
    fig.suptitle(f"Network sensitivity ({some['preset']}, {some['mix']}, N={some['robots']})")
    fig.tight_layout()
    path = out / "network.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def plot_all(records: list[Record], out: Path) -> list[Path]:
    """Every figure the records allow; returns their paths."""
    by_group: dict[str, list[Record]] = defaultdict(list)
    for r in records:
        by_group[r.get("group", "fleet")].append(r)
    paths: list[Path] = []
    if by_group["fleet"]:
        paths += plot_fleet(by_group["fleet"], out)
    if by_group["batch_cap"]:
        paths += plot_batch_cap(by_group["batch_cap"], out)
    if by_group["net_median"] or by_group["net_sigma"]:
        paths += plot_network(by_group["net_median"], by_group["net_sigma"], out)
    return paths

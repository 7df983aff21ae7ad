"""``lerobot-armory-status``: the fleet at a glance, from the server's Prometheus endpoint.

    lerobot-armory-status --metrics_url=http://127.0.0.1:9100/metrics [--watch=1]

One row per robot: tier, weight, starvation, estimated network round trip (what the server
measures; each direction is taken as half of it), age of its latest observation and of its last
chunk; then device figures, and the policy served with its live swaps (``lerobot-armory-admin``).
"""

from __future__ import annotations

import math
import sys
import time
import urllib.request
from collections import defaultdict
from dataclasses import dataclass

from prometheus_client.parser import text_string_to_metric_families

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError


@dataclass
class StatusConfig:
    """Options of ``lerobot-armory-status``.

    Attributes:
        metrics_url: the server's metrics endpoint (``--metrics_port`` of the server).
        watch: refresh every this many seconds (0: print once).
    """

    metrics_url: str = "http://127.0.0.1:9100/metrics"
    watch: float = 0.0


def fetch(url: str, timeout: float = 5.0) -> str:
    if not url.startswith(("http://", "https://")):
        raise ConfigError("metrics_url", f"must be an http(s) URL, got {url!r}")
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:  # noqa: S310 - operator-given URL
            return response.read().decode()
    except OSError as exc:
        raise ConfigError("metrics_url", f"cannot read {url}: {exc}") from None


def render(text: str) -> str:
    """The status table from a metrics exposition."""
    robots: dict[str, dict[str, float | str]] = defaultdict(dict)
    fleet: dict[str, float] = {}
    batch_sum = batch_count = 0.0
    paths: dict[str, str] = {}  # policy name -> the path it serves
    swaps: dict[str, int] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            rid = sample.labels.get("robot_id")
            if sample.name == "armory_policy_info" and sample.value == 1:
                paths[sample.labels.get("policy", "")] = sample.labels.get("path", "")
            elif sample.name == "armory_policy_swaps_total":
                swaps[sample.labels.get("result", "?")] = int(sample.value)
            elif rid is not None:
                row = robots[rid]
                row["tier"] = sample.labels.get("tier", "")
                row[sample.name] = sample.value
            elif sample.name == "armory_batch_size_sum":
                batch_sum = sample.value
            elif sample.name == "armory_batch_size_count":
                batch_count = sample.value
            elif not sample.labels:
                fleet[sample.name] = sample.value
    header = f"{'robot':<22} {'tier':<5} {'weight':>6} {'starv%':>7} {'rtt ms':>8} {'obs age ms':>10} {'chunk age ms':>12} {'chunks':>7} {'rejected':>8}"
    lines = [header, "-" * len(header)]

    def ms(v: float | str | None) -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{1000 * float(v):.0f}"

    for rid in sorted(robots):
        r = robots[rid]
        lines.append(
            f"{rid:<22} {r.get('tier', ''):<5} {float(r.get('armory_robot_weight', 1)):>6g} "
            f"{100 * float(r.get('armory_robot_starvation_ratio', 0)):>7.1f} {ms(r.get('armory_robot_round_trip_seconds')):>8} "
            f"{ms(r.get('armory_robot_observation_age_seconds')):>10} {ms(r.get('armory_robot_last_chunk_age_seconds')):>12} "
            f"{int(float(r.get('armory_robot_chunks_served_total', 0))):>7} {int(float(r.get('armory_robot_observations_rejected_total', 0))):>8}"
        )
    mean_b = batch_sum / batch_count if batch_count else 0.0
    lines.append(
        f"robots {int(fleet.get('armory_robots_connected', len(robots)))}, batches {int(batch_count)}, mean batch {mean_b:.2f}, "
        f"device busy {fleet.get('armory_device_busy_seconds_total', 0):.1f} s, "
        f"idle with work waiting {1000 * fleet.get('armory_device_idle_with_work_seconds_total', 0):.0f} ms"
    )
    if paths:
        served = (
            f"policy {next(iter(paths.values()))}"
            if len(paths) == 1
            else "policies " + ", ".join(f"{name}={path}" for name, path in sorted(paths.items()))
        )
        last = fleet.get("armory_policy_swap_seconds")
        lines.append(
            f"{served}; swaps ok {swaps.get('ok', 0)}, refused {swaps.get('refused', 0)}, failed {swaps.get('failed', 0)}"
            + (f", last took {last:.2f} s" if last else "")
        )
    return "\n".join(lines)


def _run(cfg: StatusConfig) -> None:
    while True:
        text = render(fetch(cfg.metrics_url))
        if cfg.watch > 0:
            sys.stdout.write("\x1b[2J\x1b[H" + time.strftime("%H:%M:%S ") + cfg.metrics_url + "\n" + text + "\n")
            sys.stdout.flush()
            time.sleep(cfg.watch)
        else:
            print(text)
            return


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    cfg = parse_or_exit(StatusConfig, argv, "lerobot-armory-status")
    run_or_exit(_run, cfg, "lerobot-armory-status")


if __name__ == "__main__":
    main()

"""openpi clients served batched by our endpoint vs one request at a time (openpi's own model).

N = 1..8 unchanged ``openpi-client`` clients (their own numpy<2 venv, one process, one thread
each) against ``--openpi.port``, in two settings:

- *evaluation*: clients call ``infer`` back to back (a simulated benchmark such as LIBERO's, which
  runs faster than real time; served with ``--openpi.fps=1000`` so the mirror's progress bound
  never holds a request back);
- *real-time robots*: each executes ``replan_steps`` = 5 actions at 20 fps per chunk, so it asks
  250 ms after each reply (``ActionChunkBroker``'s rhythm; ``--openpi.fps=20``).

The policy is the
analytic planner with every batch taking the H100 π0.5 profile's time (emulated: 42.3 ms at
b = 1 ... 87.2 ms at b = 5, extrapolated linearly beyond). *batched* = our server, EDF, b ≤ 8;
*one at a time* = the same server with ``--max_batch_size=1``, which is what openpi's server does
(one ``policy.infer`` per request, in arrival order). Latency = the client's ``infer`` call; chunks/s
= replies per second over all clients.

Target (evaluation, N = 8): batched serves ≥ 1.5× the chunks/s of one at a time, with a lower p90.

    .venv/bin/python benchmarks/openpi_batching.py [--duration_s=10] [--out=docs/results/openpi]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets

from tests.support.cluster import make_planner, replica_config
from tests.support.openpi_env import openpi_python

CLIENTS = ROOT / "tests" / "support" / "openpi_clients.py"
PACE_S = 5 / 20.0


def run(python: str, planner: str, batch_cap: int, n: int, duration_s: float, setting: str) -> dict:
    from lerobot_armory.entrypoints.server import build_server
    from lerobot_armory.serving.config import OpenpiOptions

    fps, pace = (1000.0, 0.0) if setting == "evaluation" else (20.0, PACE_S)
    cfg = dataclasses.replace(replica_config(planner), max_batch_size=batch_cap, openpi=OpenpiOptions(port=0, fps=fps))
    server, _ = build_server(cfg)
    try:
        with tempfile.TemporaryDirectory() as out:
            args = [python, str(CLIENTS), str(server.openpi.port), out, "bench", str(n), "0", str(duration_s), str(pace)]
            subprocess.run(args, check=True, capture_output=True, timeout=duration_s + 120)
            results = json.loads(Path(out, "results.json").read_text())
        sizes = [sum(r.startswith("openpi-") for r in b.robots) for b in server.batch_log]
    finally:
        server.stop()
    latencies = np.array([x for r in results.values() for x in r["latencies_s"][1:]]) * 1000.0  # first: connection warm-up
    replies = sum(len(r["latencies_s"]) for r in results.values())
    elapsed = max(r["elapsed_s"] for r in results.values())
    return {
        "setting": setting, "clients": n, "max_batch_size": batch_cap, "p50_ms": float(np.percentile(latencies, 50)),
        "p90_ms": float(np.percentile(latencies, 90)), "chunks_per_s": replies / elapsed,
        "mean_batch": float(np.mean(sizes)) if sizes else 0.0,
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration_s", type=float, default=10.0)
    ap.add_argument("--clients", default="1,2,4,8")
    ap.add_argument("--out", default=str(ROOT / "docs/results/openpi"))
    args = ap.parse_args()
    python = openpi_python()
    if python is None:
        print("no Python 3.10-3.12 for openpi-client's environment", file=sys.stderr)
        return 2
    planner = make_planner(Path(tempfile.mkdtemp(prefix="armory-openpi-")) / "planner")
    rows = []
    plan = [("evaluation", n) for n in (int(x) for x in args.clients.split(","))] + [("real-time robots", 4), ("real-time robots", 8)]
    for setting, n in plan:
        for cap in (8, 1):
            row = run(python, planner, cap, n, args.duration_s, setting)
            rows.append(row)
            print(
                f"{setting} N={n} {'batched b<=8' if cap == 8 else 'one at a time'}: p50 {row['p50_ms']:.0f} ms, "
                f"p90 {row['p90_ms']:.0f} ms, {row['chunks_per_s']:.1f} chunks/s, mean batch {row['mean_batch']:.2f}",
                file=sys.stderr,
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "batching.json").write_text(json.dumps({"duration_s": args.duration_s, "pace_s": PACE_S, "rows": rows}, indent=2) + "\n")
    lines = [
        "# openpi clients: batched by lerobot-armory vs one request at a time",
        "",
        "Unchanged `openpi-client` 0.1.2 clients (numpy<2 venv). *evaluation*: back to back; *real-time robots*: "
        f"{PACE_S * 1000:.0f} ms after each reply (5 actions at 20 fps). {args.duration_s:g} s per row; planner policy with "
        "the H100 π0.5 latency profile emulated (CPU machine; b > 5 extrapolated). One at a time = the same server "
        "at `--max_batch_size=1`, as openpi's server runs. Command: `.venv/bin/python benchmarks/openpi_batching.py`.",
        "",
        "| setting | clients | served | p50 ms | p90 ms | chunks/s | mean batch |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        served = "batched (b ≤ 8)" if r["max_batch_size"] == 8 else "one at a time"
        lines.append(f"| {r['setting']} | {r['clients']} | {served} | {r['p50_ms']:.0f} | {r['p90_ms']:.0f} | {r['chunks_per_s']:.1f} | {r['mean_batch']:.2f} |")
    (out / "batching.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    targets = Targets()
    evaluation = [r for r in rows if r["setting"] == "evaluation"]
    n_max = max(r["clients"] for r in evaluation)
    ours = next(r for r in evaluation if r["clients"] == n_max and r["max_batch_size"] == 8)
    one = next(r for r in evaluation if r["clients"] == n_max and r["max_batch_size"] == 1)
    targets.check_min(f"N={n_max}: batched chunks/s over one at a time", ours["chunks_per_s"] / one["chunks_per_s"], 1.5, "x")
    targets.check(f"N={n_max}: batched p90 over one at a time", ours["p90_ms"] / one["p90_ms"], 1.0, "x")
    targets.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())

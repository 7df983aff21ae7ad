"""Task success side by side with LeRobot's async inference: one checkpoint, the same MetaWorld robots.

    python benchmarks/tasks/vs_lerobot_async_tasks.py --out=docs/results/tasks        # everything (~45 min)
    python benchmarks/tasks/vs_lerobot_async_tasks.py --tasks=reach-moving --robots=1 --episodes=5 --seed=0

For each task (its checkpoint from examples/checkpoints), fleet size N and system, N MetaWorld
robots (one process each) step their simulators at 30 Hz on the wall clock, holding when starved,
until each has run ``--episodes`` episodes (robot ``k`` on seeds ``seed + 100·k`` on: every system
runs exactly the same episodes, so success rates compare seed for seed; successes per minute is
over the time each robot took):

- ``ours``: one ``lerobot-armory-server`` for the fleet (its default scheduler, batch cap N), the
  robots on our client (``--h_min=10 --h_max=20``, episode boundaries sent);
- ``stock``: LeRobot's ``policy_server`` + ``robot_client`` as shipped — one server per robot (a
  stock server serves one client), ``actions_per_chunk=20``, ``chunk_size_threshold=0.5`` (a new
  chunk asked with 10 of 20 actions left, as ours asks after 10 executed), its similarity filter
  and its ``weighted_average`` merge of overlapping chunks;
- ``stock_nofilter``: the same with the filter patched off;
- ``stock_latest``: filter off and ``aggregate_fn_name=latest_only`` (switch to the newest chunk,
  as ours does) — stock tuned as far as its options go;
- ``stock_reset``: ``stock_latest`` plus our episode boundary grafted onto the stock client (the
  launcher empties its queue at a reset and drops chunks of observations taken before it): what
  is left of the difference once the protocol's episode boundary is taken out.

Every stock run needs one adapter, without which a stock server cannot run these checkpoints at
all: the stock client puts every float of the robot into ``observation.state`` and the stock
server passes only that and the images to the policy, so ``benchmarks/_stock_async.py
--environment_state`` moves the ``environment_state.*`` floats into
``observation.environment_state`` (the split our client makes). Stock has no episode boundary: at
a reset its robot executes what is left of the old episode's chunk, as any stock user's would.

Per run: episodes finished, successes, success rate (Wilson 95 %), successes per minute per robot,
starvation (mean, max), chunk latency p50, server RSS (summed over stock's servers). Writes
``vs_lerobot_async.json`` under ``--out`` after every run, prints the table; exits 1 if a run fails.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import vs_lerobot_async as vs  # noqa: E402  the side-by-side machinery (processes, /proc sampling)
from _checkpoints import CHECKPOINTS  # noqa: E402  benchmarks/tasks/: the script's own directory

from lerobot_armory.bench.tasks import wilson  # noqa: E402

FPS, H_MIN, H_MAX = 30, 10, 20
THRESHOLD = 0.5  # stock asks with <= 10 of 20 actions left: after 10 executed, as ours
SEED_STRIDE = 100  # robot k's seeds start at seed + 100 k: no two robots share an episode's seed
# system -> (stock's similarity filter off?, stock's merge of overlapping chunks, episode boundary
# grafted on?); None: ours
SYSTEMS: dict[str, tuple[bool, str, bool] | None] = {
    "ours": None,
    "stock": (False, "weighted_average", False),
    "stock_nofilter": (True, "weighted_average", False),
    "stock_latest": (True, "latest_only", False),
    "stock_reset": (True, "latest_only", True),
}


def options(policy: Path, n: int, duration_s: float) -> vs.Options:
    """The side-by-side bench's options for one run (only what its helpers read)."""
    return vs.Options(
        robots=[n], duration_s=duration_s, systems=[], device="cpu", ours_cpu_threads=[None],
        ours_scheduler="lookahead", max_batch_size=max(n, 1), stock_cpu_threads=0, scene="static",
        policy=str(policy), out=None, work_dir=None, stock_shared_server=False, chunk=H_MAX,
    )  # fmt: skip


def robot_spec(
    task: str, k: int, seed: int, address: str, policy: Path, stock: tuple[bool, str, bool] | None, duration_s: float, run_dir: Path
) -> dict[str, Any]:
    """Robot ``k``'s spec for ``benchmarks/_ours_robot.py`` or ``_stock_async.py client``."""
    return {
        "robot_kind": "metaworld", "task": task, "robot_id": f"robot{k}", "seed": seed + SEED_STRIDE * k,
        "fps": FPS, "h_min": H_MIN, "h_max": H_MAX, "actions_per_chunk": H_MAX, "chunk_size_threshold": THRESHOLD,
        "aggregate_fn_name": stock[1] if stock else "", "episode_reset": bool(stock and stock[2]), "settle_chunks": 1, "address": address, "policy_path": str(policy),
        "policy_type": vs.policy_type(str(policy)), "device": "cpu", "duration_s": duration_s,
        "ready_path": str(run_dir / f"ready{k}"), "go_path": str(run_dir / "go"), "stats_path": str(run_dir / f"robot{k}.json"),
    }  # fmt: skip


def run_one(task: str, system: str, n: int, seed: int, episodes: int, duration_s: float, work: Path) -> dict[str, Any]:
    """One system serving ``n`` robots on ``task``; its record."""
    policy = CHECKPOINTS[task]
    opts = options(policy, n, duration_s)
    run_dir = work / f"{task}-{system}-N{n}"
    run_dir.mkdir(parents=True, exist_ok=True)
    stock = SYSTEMS[system]
    fleet = vs.Fleet()
    t0 = time.monotonic()
    try:
        if stock is None:
            proc, address = vs.start_ours_server(opts, None, run_dir)
            fleet.servers.append(proc)
            addresses = [address] * n
        else:
            started = vs.start_stock_servers(opts, n, stock[0], run_dir, ("--environment_state",))
            fleet.servers.extend(p for p, _ in started)
            addresses = [a for _, a in started]
        for k in range(n):
            spec = {**robot_spec(task, k, seed, addresses[k], policy, stock, duration_s, run_dir), "episodes": episodes}
            fleet.clients.append(vs.start_client("ours" if stock is None else "stock", spec, k, run_dir))
        vs.wait_clients_ready(fleet, run_dir)
        fleet.ready_s = time.monotonic() - t0
        usage = vs.measure(fleet, run_dir, duration_s, f"{system} {task} N={n}")
    finally:
        fleet.stop()
    robots = vs.read_robot_stats(run_dir, n, f"{system} {task} N={n}")
    summary = vs.summarize(robots)
    episodes = sum(r["episodes_done"] for r in robots)
    wins = sum(r["successes"] for r in robots)
    minutes = sum(r["wall_s"] for r in robots) / 60.0
    for r in robots:  # keep each robot's latency quantiles and results, not every chunk's latency
        lat = r.pop("latency_ms")
        r.update(latency_p50_ms=vs.percentile(lat, 0.5), latency_p90_ms=vs.percentile(lat, 0.9))
    return {
        "task": task, "system": system, "robots": n, "episodes": episodes, "successes": wins,
        "success_rate": wins / episodes if episodes else None, "interval95": list(wilson(wins, episodes)),
        "successes_per_min_per_robot": wins / minutes if minutes else 0.0,
        "stale_episode_chunks": sum(r.get("stale_episode_chunks", 0) for r in robots),
        **summary, **usage, "ready_s": fleet.ready_s, "per_robot": robots,
    }  # fmt: skip


def table(runs: list[dict[str, Any]]) -> str:
    """The markdown table, one row per task × N × system."""
    head = (
        "| task | N | system | successes | rate [95 %] | succ/min/robot | starved mean % | starved max % | "
        "latency p50 ms | server RSS GiB | machine busy % |"
    )
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in runs:
        lo, hi = r["interval95"]
        rate = f"{r['success_rate']:.2f} [{lo:.2f}, {hi:.2f}]" if r["episodes"] else "–"
        lines.append(
            f"| {r['task']} | {r['robots']} | {r['system']} | {r['successes']}/{r['episodes']} | {rate} | "
            f"{r['successes_per_min_per_robot']:.1f} | {r['starvation_mean_pct']:.1f} | {r['starvation_max_pct']:.1f} | "
            f"{r['latency_p50_ms']:.0f} | {r['server_rss_peak_bytes'] / 2**30:.2f} | {r['machine_busy_pct']:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", default="reach-moving,push", help=f"comma-separated: {', '.join(CHECKPOINTS)}")
    ap.add_argument("--robots", default="1,2,4", help="fleet sizes N, comma-separated")
    ap.add_argument("--systems", default=",".join(SYSTEMS), help=f"comma-separated: {', '.join(SYSTEMS)}")
    ap.add_argument("--episodes", type=int, default=15, help="episodes per robot")
    ap.add_argument("--duration_s", type=float, default=300.0, help="longest a run may take (its robots stop there)")
    ap.add_argument("--seed", type=int, default=1000, help="robot k's first seed is seed + 100 k (evaluation: 1000 up)")
    ap.add_argument("--out", help="write vs_lerobot_async.json here (e.g. docs/results/tasks)")
    ap.add_argument("--work_dir", help="logs and per-robot stats (default: a temporary directory)")
    ap.add_argument("--append", action="store_true", help="add the runs to OUT/vs_lerobot_async.json's")
    a = ap.parse_args(argv)
    tasks = [t.strip() for t in a.tasks.split(",") if t.strip()]
    systems = [s.strip() for s in a.systems.split(",") if s.strip()]
    sizes = vs.int_list(a.robots)
    if bad := [t for t in tasks if t not in CHECKPOINTS] + [s for s in systems if s not in SYSTEMS]:
        ap.error(f"unknown task(s) or system(s): {', '.join(bad)}")
    if not sizes or min(sizes) < 1 or a.duration_s <= 0 or a.episodes < 1:
        ap.error("--robots must be positive integers, --episodes >= 1 and --duration_s > 0")
    work = Path(a.work_dir or tempfile.mkdtemp(prefix="vs-stock-tasks-")).resolve()
    command = "python benchmarks/tasks/vs_lerobot_async_tasks.py " + " ".join(map(shlex.quote, sys.argv[1:] if argv is None else argv))
    todo = [(t, n, s) for t in tasks for n in sizes for s in systems]  # systems interleaved: drift hits all alike
    print(f"{len(todo)} run(s) of {a.episodes} episodes per robot (at most {a.duration_s:g} s); logs in {work}", flush=True)
    report: dict[str, Any] = {
        "command": command, "machine": vs.machine(), "fps": FPS, "h_min": H_MIN, "h_max": H_MAX,
        "chunk_size_threshold": THRESHOLD, "episodes_per_robot": a.episodes, "duration_s_cap": a.duration_s, "seed": a.seed, "runs": [],
    }  # fmt: skip
    if a.append and a.out and (Path(a.out) / "vs_lerobot_async.json").is_file():
        before = json.loads((Path(a.out) / "vs_lerobot_async.json").read_text())
        report["runs"], report["command"] = before["runs"], f"{before['command']} ; then {command}"
    try:
        for k, (task, n, system) in enumerate(todo):
            print(f"[{k + 1}/{len(todo)}] {task} N={n} {system} ...", flush=True)
            r = run_one(task, system, n, a.seed, a.episodes, a.duration_s, work)
            report["runs"].append(r)
            print(f"    {r['successes']}/{r['episodes']} successes, {r['successes_per_min_per_robot']:.1f}/min per robot, "
                  f"starved {r['starvation_mean_pct']:.1f} %, servers {r['server_rss_peak_bytes'] / 2**30:.2f} GiB", flush=True)  # fmt: skip
            if a.out:
                Path(a.out).mkdir(parents=True, exist_ok=True)
                (Path(a.out) / "vs_lerobot_async.json").write_text(json.dumps(report, indent=2) + "\n")
    except vs.RunFailed as exc:
        print(f"vs_lerobot_async_tasks: error: {exc}", file=sys.stderr)
        return 1
    print()
    print(table(report["runs"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())

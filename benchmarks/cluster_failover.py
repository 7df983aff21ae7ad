"""Failover of a live cluster on a local Ray cluster: replica actors killed under a running fleet.

3 CPU replicas (Ray actors; the armory_planner, batches taking the H100 π0.5 profile's time),
6 armory_sim robots (3 fast, 3 slow, 20 fps) registered through the front. Every ``--every_s``
seconds the replica serving ``robotK`` is killed (``ray.kill``: its process dies; Ray restarts
it). For each kill: how long each of its robots held before executing again (outage), whether any
executed an action of the dead session (stale), how long Ray took to bring the replica back as
the front sees it, and the moves the front made to rebalance onto it.

Targets: every outage < 3 s, no stale action, every killed replica back up.

    .venv/bin/python benchmarks/cluster_failover.py [--kills=3] [--every_s=6] [--out=docs/results/cluster]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets

from tests.support.cluster import make_planner, replica_config, stale_actions, start_fleet, wait_for


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=3)
    ap.add_argument("--every_s", type=float, default=6.0)
    ap.add_argument("--out", default=str(ROOT / "docs/results/cluster"))
    args = ap.parse_args()

    import ray

    from lerobot_armory.entrypoints.cluster.cli import ClusterConfig, RayOptions, ReplicaOptions, start_replicas
    from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer

    work = Path(tempfile.mkdtemp(prefix="armory-failover-"))
    planner = make_planner(work / "planner")
    ray.init(num_cpus=6, include_dashboard=False, namespace="armory-failover", log_to_driver=False, configure_logging=False)
    base = replica_config(planner)
    cfg = ClusterConfig(
        **{name: getattr(base, name) for name in base.__dataclass_fields__},
        replicas=3,
        ray=RayOptions(None, "armory-failover"),
        replica=ReplicaOptions(num_gpus=0.0, num_cpus=1.0),
    )
    replicas = start_replicas(cfg)
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.25)))
    duration = args.every_s * (args.kills + 1) + 4.0
    print(f"6 robots for {duration:.0f} s; a replica killed every {args.every_s:g} s, {args.kills} times", file=sys.stderr)
    robots = start_fleet(front.address, n=6, duration_s=duration)
    assert wait_for(lambda: len(front.front.placements()) == 6, timeout=10)
    placed = front.front.placements()
    kills = []
    t0 = time.monotonic()
    for k in range(args.kills):
        time.sleep(max(0.0, t0 + args.every_s * (k + 1) - time.monotonic()))
        where = front.front.placements()
        victim = where.get(f"robot{k % 6}") or sorted(set(where.values()))[0]
        on_it = sorted(r for r, rid in where.items() if rid == victim)
        t_kill = time.monotonic()
        ray.kill(replicas.handles[victim], no_restart=False)
        wait_for(lambda v=victim: not front.front.state[v].view.healthy, timeout=5, step=0.01)
        back = wait_for(lambda v=victim: front.front.state[v].view.healthy, timeout=60, step=0.05)
        kills.append({"replica": victim, "robots": on_it, "restart_s": time.monotonic() - t_kill if back else None})
        print(f"kill {k + 1}: {victim} ({', '.join(on_it)}); Ray had it back in {kills[-1]['restart_s']:.1f} s", file=sys.stderr)
    stats = {r.client.identity.robot_id: (r, r.join()) for r in robots}
    moves = [m.__dict__ for m in front.front.moves]
    front.stop(0)
    for handle in replicas.handles.values():
        ray.kill(handle, no_restart=True)
    ray.shutdown()

    outages = {rid: s["outages_s"] for rid, (_, s) in stats.items()}
    stale = {rid: len(stale_actions(r.client)) for rid, (r, _) in stats.items()}
    every = [o for v in outages.values() for o in v]
    tiers: dict[str, list[float]] = {}
    for _, s in stats.values():
        tiers.setdefault(s["tier"], []).append(s["starvation_pct"])
    result = {
        "placement_at_start": placed,
        "robots_per_replica_at_start": dict(Counter(placed.values())),
        "kills": kills,
        "outages_s": outages,
        "stale_actions": stale,
        "moves": moves,
        "starvation_pct_by_tier": {t: statistics.mean(v) for t, v in tiers.items()},
        "duration_s": duration,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "failover.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# Failover on a local Ray cluster",
        "",
        f"3 CPU replicas (Ray actors), 6 armory_sim robots (3 fast, 3 slow, 20 fps), {duration:.0f} s; a replica actor "
        f"killed every {args.every_s:g} s ({args.kills} kills). Command: `.venv/bin/python benchmarks/cluster_failover.py`.",
        "",
        f"Placement at start (robots per replica): {dict(sorted(Counter(placed.values()).items()))}",
        "",
        "| kill | replica | its robots | Ray restart (kill → front sees it up) |",
        "|---|---|---|---|",
    ]
    for k, kill in enumerate(kills, 1):
        restart = f"{kill['restart_s']:.1f} s" if kill["restart_s"] is not None else "not back in 60 s"
        lines.append(f"| {k} | {kill['replica']} | {', '.join(kill['robots'])} | {restart} |")
    lines += [
        "",
        "| robot | outages (s): lost connection → next executed action | stale actions |",
        "|---|---|---|",
    ]
    for rid in sorted(outages):
        lines.append(f"| {rid} | {', '.join(f'{o:.2f}' for o in outages[rid]) or '-'} | {stale[rid]} |")
    lines += [
        "",
        f"Outages: {len(every)}, max {max(every, default=0):.2f} s, median {statistics.median(every) if every else 0:.2f} s. "
        f"Rebalancing moves (between chunks): {len(moves)}. Mean starvation over the whole run (kills included): "
        + ", ".join(f"{t} {v:.1f} %" for t, v in sorted(result["starvation_pct_by_tier"].items()))
        + ".",
    ]
    (out / "failover.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    targets = Targets()
    targets.check("longest outage (lost connection -> next executed action)", max(every, default=0.0), 3.0, "s")
    targets.check("stale actions executed", float(sum(stale.values())), 0.0, "")
    targets.check("killed replicas not back up within 60 s", float(sum(k["restart_s"] is None for k in kills)), 0.0, "")
    targets.check_min("killed replicas' robots that saw an outage", float(sum(bool(outages[r]) for k in kills for r in k["robots"])),
                      float(sum(len(k["robots"]) for k in kills)), "")
    targets.finish()
    return 0

if __name__ == "__main__":
    sys.exit(main())

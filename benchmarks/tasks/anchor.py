"""The correctness anchor at full size: each committed checkpoint, LeRobot's loop against served.

    python benchmarks/tasks/anchor.py --episodes=100 --out=docs/results/tasks    # ~10 min on 2 cores

For each task: the checkpoint in LeRobot's own ``select_action`` loop (``n_action_steps`` =
h_min = 10), the same loop made asynchronous with a constant 1-tick delay (what a served robot
with a fast server sees: the chunk of the observation at index i arrives at i + 1; the robot's own
action buffer switches), and served through ``lerobot-armory-server`` to one ``metaworld`` robot
at 30 Hz (h_min 10, h_max 20, no added latency), and through the server's openpi endpoint to a
client asking as openpi's does (synchronous: the world waits, 10 actions per chunk), all on seeds
1000 .. 1000 + episodes - 1, plus how many openpi episodes ended exactly as LeRobot's loop's (same
success at the same tick). The anchor holds when the served and the openpi success rates lie
inside the 95 % (Wilson) interval of LeRobot's loop. Writes ``anchor.json`` and prints the table;
exits 1 where the anchor does not hold. ``--keep=delayed,served`` keeps those columns from the
``anchor.json`` already in ``--out`` (same episodes) instead of running them again.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from lerobot_armory.bench.tasks import TasksConfig, run_local, run_openpi, run_served
from _checkpoints import CHECKPOINTS  # benchmarks/tasks/: the script's own directory



def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--tasks", default=",".join(CHECKPOINTS))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--keep", default="", help="columns kept from OUT/anchor.json: delayed, served (comma-separated)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    keep = {k.strip() for k in args.keep.split(",") if k.strip()}
    if keep - {"delayed", "served"}:
        ap.error(f"--keep: only delayed and served can be kept, got {sorted(keep)}")
    old, command = {}, ""
    if keep:
        before = json.loads((args.out / "anchor.json").read_text())
        old = {r["task"]: r for r in before["rows"] if r["episodes"] == args.episodes}
        command = before["command"]
    rows, failed = [], []
    for task in args.tasks.split(","):
        cfg = TasksConfig(policy_path=str(CHECKPOINTS[task]), task=task, mode="both", episodes=args.episodes, max_minutes=20.0)
        cfg.validate()
        if keep and task not in old:
            ap.error(f"--keep: {args.out / 'anchor.json'} has no {task} row of {args.episodes} episodes")
        local = run_local(cfg)
        delayed = old[task]["local_delayed_1_tick"] if "delayed" in keep else run_local(replace(cfg, latency_ticks=1))
        if "served" in keep:
            served = {**old[task]["served"], "episodes": old[task]["served_episodes"]}
        else:
            served = run_served(cfg, Path(tempfile.mkdtemp(prefix="armory-anchor-")))
        openpi = run_openpi(replace(cfg, mode="openpi"))
        same = sum(
            (a["success"], a["ticks"]) == (b["success"], b["ticks"])
            for a, b in zip(local["episode_results"], openpi["episode_results"], strict=True)
        )
        lo, hi = local["interval95"]
        holds = lo <= served["success_rate"] <= hi and lo <= openpi["success_rate"] <= hi
        failed += [] if holds else [task]
        rows.append({
            "task": task, "episodes": args.episodes, "holds": holds,
            "local": {k: local[k] for k in ("successes", "success_rate", "interval95")},
            "local_delayed_1_tick": {k: delayed[k] for k in ("successes", "success_rate", "interval95")},
            "served": {k: served[k] for k in ("successes", "success_rate", "interval95", "starvation_pct", "successes_per_min", "stale_episode_chunks")},
            "served_episodes": served["episodes"],
            "openpi": {k: openpi[k] for k in ("successes", "success_rate", "interval95")},
            "openpi_same_as_local": same,
        })  # fmt: skip
        commands = [command, " ".join(sys.argv)] if keep else [" ".join(sys.argv)]
        (args.out / "anchor.json").write_text(json.dumps({"command": " ; then ".join(commands), "rows": rows}, indent=2) + "\n")
    print(
        "| task | LeRobot's loop [95 %] | the same, 1-tick delay | served (N = 1, 30 Hz) | served starved % | succ/min "
        "| openpi endpoint | openpi episodes = LeRobot's | anchor |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = []
        for key in ("local", "local_delayed_1_tick", "served", "openpi"):
            v = r[key]
            lo, hi = v["interval95"]
            cells.append(f"{v['successes']}/{r['episodes'] if key != 'served' else r['served_episodes']} = {v['success_rate']:.2f} [{lo:.2f}, {hi:.2f}]")
        print(
            f"| {r['task']} | {' | '.join(cells[:3])} | {r['served']['starvation_pct']:.1f} | {r['served']['successes_per_min']:.1f} | "
            f"{cells[3]} | {r['openpi_same_as_local']}/{r['episodes']} | {'holds' if r['holds'] else 'FAILS'} |"
        )
    if failed:
        print(f"the anchor does not hold for: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Scripted-expert demonstrations of a MetaWorld task, written with LeRobot's own dataset API.

    python benchmarks/tasks/record_demos.py --task=push --episodes=60 --root=out/tasks/data/push

Each episode is one seed (``--seed_base`` + k) run by the task's scripted expert from the live
state until success or the time limit; only successful episodes are kept (the expert solves
both tasks every time on the seeds tried). The dataset is LeRobotDataset v3
(``create`` / ``add_frame`` / ``save_episode`` / ``finalize``): ``observation.state`` (4),
``observation.environment_state`` (39, or 42 on the dynamic task), ``action`` (4), at the
robot's control rate. Prints the dataset's sha256 (over its files, sorted), which the trained
checkpoint's README records.

Evaluation seeds (1,000 and up, see ``lerobot_armory/robot/metaworld``) never overlap the
demonstration seeds (0 .. 999).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from lerobot_armory.robot.metaworld.tasks import ACTION_NAMES, STATE_NAMES, MetaWorldTask, task_spec


def dataset_sha256(root: Path) -> str:
    """sha256 over every file of the dataset (relative path and bytes, in sorted order; JSON files
    with sorted keys, since LeRobot writes meta/stats.json's keys in no fixed order)."""
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode())
        data = path.read_bytes()
        if path.suffix == ".json":
            data = json.dumps(json.loads(data), sort_keys=True).encode()
        h.update(data)
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="push")
    ap.add_argument("--episodes", type=int, default=60)
    ap.add_argument("--seed_base", type=int, default=0)
    ap.add_argument("--fps", type=int, default=30)
    ap.add_argument("--root", type=Path, required=True)
    args = ap.parse_args()
    warnings.filterwarnings("ignore", message="Constant")  # MetaWorld's experts warn on every clipped action
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    spec = task_spec(args.task)
    if args.seed_base + args.episodes > 1000:
        print("error: demonstration seeds must stay below 1000 (the evaluation seeds)", file=sys.stderr)
        return 2
    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": list(STATE_NAMES)},
        "observation.environment_state": {"dtype": "float32", "shape": (spec.env_state_dim,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": list(ACTION_NAMES)},
    }
    if args.root.exists():
        shutil.rmtree(args.root)
    ds = LeRobotDataset.create(
        repo_id=f"local/metaworld_{spec.name}", fps=args.fps, features=features, root=args.root,
        robot_type="metaworld", use_videos=False,
    )  # fmt: skip
    task = MetaWorldTask(spec.name)
    t0 = time.time()
    kept = frames = 0
    for k in range(args.episodes):
        task.reset(args.seed_base + k)
        buffered = []
        while True:
            action = task.expert_action()
            buffered.append((task.agent_state(), task.environment_state(), action))
            if task.step(action).done:
                break
        if not task.success:
            print(f"seed {args.seed_base + k}: the expert failed, episode dropped", file=sys.stderr)
            continue
        for state, env_state, action in buffered:
            ds.add_frame({
                "observation.state": state, "observation.environment_state": env_state,
                "action": np.asarray(action, np.float32), "task": spec.description,
            })  # fmt: skip
        ds.save_episode()
        kept += 1
        frames += len(buffered)
    ds.finalize()
    print(f"{spec.name}: {kept}/{args.episodes} expert episodes kept, {frames} frames, {time.time() - t0:.1f} s")
    print(f"dataset sha256 {dataset_sha256(args.root)}  ({args.root})")
    return 0 if kept else 1


if __name__ == "__main__":
    sys.exit(main())

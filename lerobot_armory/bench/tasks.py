"""``lerobot-armory-tasks``: a trained policy's task success, run locally and served to a fleet.

    lerobot-armory-tasks --policy_path=examples/checkpoints/metaworld-push-act --task=push --episodes=20

Two ways to run the same checkpoint on the same MetaWorld seeds:

- ``local``: LeRobot's own evaluation loop (what ``lerobot-eval`` does: the checkpoint's saved
  pre/post processors, ``policy.reset()`` at every episode, ``select_action`` every tick), in
  simulated time, as fast as the CPU allows;
- ``served``: the real ``lerobot-armory-server`` serving the checkpoint (optionally with an
  emulated GPU latency profile) to ``--robots`` ``metaworld`` robots, each stepping its simulator
  at ``--fps`` on the wall clock over the real gRPC protocol, holding when starved;
- ``openpi``: the real server's openpi endpoint (``--openpi.port``), driven as openpi's own client
  drives a policy in its LIBERO evaluation: one ``infer`` per ``h_min`` actions, the world
  waiting for each answer (simulated time), over openpi's websocket + msgpack wire.

It prints, per robot and for the fleet, episodes, successes, the success rate with its 95 %
(Wilson) interval, successes per minute and starvation; with ``--mode=both`` it says whether the
served success rate lies inside the local run's 95 % interval (the correctness anchor: serving
must not cost a checkpoint its task success). Robot ``k`` runs seeds ``seed + k·episodes`` on,
so a fleet covers exactly the seeds a local run of ``robots · episodes`` episodes does.
"""

from __future__ import annotations

import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.bench.live import start_server, stop_all
from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot.metaworld.tasks import TASKS

MODES = ("local", "served", "openpi", "both")
OPENPI_MAX_BYTES = 64 << 20  # the largest reply this evaluation accepts


@dataclass
class TasksConfig:
    """Options of ``lerobot-armory-tasks``.

    Attributes:
        policy_path: the checkpoint (a LeRobot policy directory or hub id), trained on the task;
            with several tasks, one per task: ``push=DIR,reach-moving=DIR`` (served as
            ``--policies``, each robot registering for its task's policy).
        task: the MetaWorld task (``push``: static; ``reach-moving``: dynamic), or several,
            comma-separated: robot ``k`` runs the ``k mod n``-th (a mixed fleet; dynamic robots
            are the fast tier).
        mode: ``local`` (LeRobot's loop), ``served`` (through the fleet), ``both``, or
            ``openpi`` (through the server's openpi endpoint, as openpi's client asks).
        robots: fleet size N (served).
        episodes: episodes per robot (local: ``robots · episodes`` in all); 0 with
            ``duration_s``: as many as fit.
        duration_s: served: stop every robot after this many seconds (0: after its episodes).
        fast_weight: the weight dynamic-task robots ask for (Lookahead's), granted by the
            server's grant rules.
        seed: the first episode's seed (evaluation seeds are 1000 and up).
        fps: the robots' control rate (served).
        h_min / h_max: the robots' horizons (served): served again after ``h_min`` executed
            actions, at most ``h_max`` actions of a chunk executed.
        n_action_steps: actions executed per chunk in the local loop (default: ``h_min``, so the
            two runs re-plan equally often).
        latency_ticks: local: LeRobot's loop made asynchronous as a served robot is: a chunk is
            asked for after ``h_min`` executed actions and arrives this many ticks later,
            meanwhile the arm executes the chunk it holds (or holds, starved), then switches at
            the current index, up to ``h_max`` actions of a chunk (0: LeRobot's synchronous
            ``select_action`` loop). The served run at that delay should match it.
        scheduler: ``--scheduler.type`` of the server.
        max_batch_size: the server's batch cap.
        emulate_profile: a latency profile the server replays (``l40s-pi05``, ``h200-pi05``, a
            file); empty: the checkpoint's real timing on this CPU.
        server_args: more server options, space-separated.
        groups: robot processes (robots are spread over them).
        max_minutes: give up a served run after this long (its robots' partial results are kept).
        output: write the results as JSON here.
    """

    policy_path: str = ""
    task: str = "push"
    mode: str = "both"
    robots: int = 1
    episodes: int = 20
    duration_s: float = 0.0
    fast_weight: float = 1.0
    seed: int = 1000
    fps: float = 30.0
    h_min: int = 10
    h_max: int = 20
    n_action_steps: int | None = None
    latency_ticks: int = 0
    scheduler: str = "edf"
    max_batch_size: int = 8
    emulate_profile: str = ""
    server_args: str = ""
    groups: int = 1
    max_minutes: float = 30.0
    output: str | None = None

    def validate(self) -> None:
        if not self.policy_path:
            raise ConfigError("policy_path", "name the checkpoint to evaluate (a LeRobot policy directory or hub id)")
        if self.mode not in MODES:
            raise ConfigError("mode", f"must be one of {', '.join(MODES)}, got {self.mode!r}")
        for task in self.tasks:
            if task not in TASKS:
                raise ConfigError("task", f"unknown task {task!r}: known tasks are {', '.join(sorted(TASKS))}")
        paths = self.policy_paths  # raises on a bad mapping
        missing = [t for t in self.tasks if t not in paths]
        if missing:
            raise ConfigError("policy_path", f"no checkpoint for task(s) {', '.join(missing)}: write task=DIR for each")
        if self.robots < 1 or self.episodes < 0 or (self.episodes == 0 and self.duration_s <= 0):
            raise ConfigError("robots", "robots must be >= 1 and episodes >= 1 (or 0 with duration_s > 0)")
        if self.mode != "served" and (self.episodes == 0 or len(self.tasks) > 1):
            raise ConfigError("mode", f"a {self.mode} run needs one task and episodes >= 1: use --mode=served")
        if self.latency_ticks < 0:
            raise ConfigError("latency_ticks", f"must be >= 0, got {self.latency_ticks}")
        if not self.fast_weight > 0:
            raise ConfigError("fast_weight", f"must be > 0, got {self.fast_weight}")
        if not 0 < self.fps <= 1000:
            raise ConfigError("fps", f"must be in (0, 1000], got {self.fps}")
        if not 1 <= self.h_min <= self.h_max:
            raise ConfigError("h_min", f"need 1 <= h_min <= h_max, got {self.h_min}, {self.h_max}")


    @property
    def tasks(self) -> list[str]:
        return [t.strip() for t in self.task.split(",") if t.strip()]

    @property
    def policy_paths(self) -> dict[str, str]:
        """``{task: checkpoint}``: one path for every task, or ``task=path`` pairs."""
        if "=" not in self.policy_path:
            return dict.fromkeys(self.tasks, self.policy_path)
        out = {}
        for pair in self.policy_path.split(","):
            task, sep, path = pair.partition("=")
            if not sep or not path.strip():
                raise ConfigError("policy_path", f"expected task=DIR pairs, got {pair!r}")
            out[task.strip()] = path.strip()
        return out


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate (``(0, 1)`` for no episodes)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


# ---- local: LeRobot's own loop ---------------------------------------------------------------


def load_local(path: str, n_action_steps: int) -> tuple[Any, Any, Any, Any]:
    """``(policy, pre, post, config)``: a checkpoint as LeRobot's evaluation loads it, on the CPU,
    executing ``n_action_steps`` actions per chunk through ``select_action``."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    config = PreTrainedConfig.from_pretrained(path)
    config.device = "cpu"
    if hasattr(config, "n_action_steps"):
        config.n_action_steps = n_action_steps
    policy = get_policy_class(config.type).from_pretrained(path, config=config)
    policy.eval()
    pre, post = make_pre_post_processors(config, pretrained_path=path)
    return policy, pre, post, config


def observation_of(task: Any) -> dict[str, Any]:
    """A MetaWorld task's current observation as the checkpoints read it (a batch of one)."""
    import torch

    return {
        "observation.state": torch.from_numpy(task.agent_state()).unsqueeze(0),
        "observation.environment_state": torch.from_numpy(task.environment_state()).unsqueeze(0),
        "task": [task.spec.description],
    }


def run_local(cfg: TasksConfig) -> dict[str, Any]:
    """The checkpoint in LeRobot's evaluation loop, one episode per seed (simulated time)."""
    import torch

    from lerobot_armory.robot.metaworld.tasks import MetaWorldTask

    policy, pre, post, config = load_local(cfg.policy_paths[cfg.tasks[0]], cfg.n_action_steps or cfg.h_min)
    task = MetaWorldTask(cfg.tasks[0])
    results = []
    t0 = time.monotonic()
    total = cfg.robots * cfg.episodes
    for k in range(total):
        seed = cfg.seed + k
        task.reset(seed)
        policy.reset()
        if cfg.latency_ticks == 0:
            while True:
                with torch.inference_mode():
                    action = post(policy.select_action(pre(observation_of(task))))
                if task.step(action.squeeze(0).cpu().numpy()).done:
                    break
        else:
            _run_delayed(cfg, task, lambda: chunk_of(policy, pre, post, observation_of(task)))
        results.append({"seed": seed, "success": bool(task.success), "ticks": task.ticks})
        _progress("local", results, total, t0)
    steps = config.n_action_steps if hasattr(config, "n_action_steps") else None
    return episode_summary("local", results, n_action_steps=steps, latency_ticks=cfg.latency_ticks)


def episode_summary(mode: str, results: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    """A run's record: episodes, successes, the success rate with its 95 % interval, ``extra``,
    and each episode's result (seed, success, ticks)."""
    wins, n = sum(r["success"] for r in results), len(results)
    return {
        "mode": mode, "episodes": n, "successes": wins, "success_rate": wins / n if n else 0.0,
        "interval95": wilson(wins, n), **extra, "episode_results": results,
    }  # fmt: skip


def _progress(label: str, results: list[dict[str, Any]], total: int, t0: float) -> None:
    """A progress line every 10 episodes and at the last."""
    if len(results) % 10 == 0 or len(results) == total:
        wins = sum(r["success"] for r in results)
        print(f"  {label}: {len(results)}/{total} episodes, {wins} successes ({time.monotonic() - t0:.0f} s)", flush=True)


# ---- served: the fleet -----------------------------------------------------------------------


def chunk_of(policy: Any, pre: Any, post: Any, obs: dict[str, Any]) -> np.ndarray:
    """The policy's whole chunk for one observation, in the robot's action space."""
    import torch

    with torch.inference_mode():
        chunk = policy.predict_action_chunk(pre(obs))  # (1, H, action_dim), normalised
        return post(chunk).squeeze(0).cpu().numpy()


def _run_delayed(cfg: TasksConfig, task: Any, chunk_of: Any) -> None:
    """One episode executed as a served robot executes it, with a constant delay of
    ``cfg.latency_ticks`` ticks from an observation to its chunk (the robot's own action buffer)."""
    from lerobot_armory.robot.actions import ActionBuffer

    buffer = ActionBuffer(cfg.h_max)
    pending: list[tuple[int, int, np.ndarray]] = []  # (arrival tick, i_start, actions)
    index, tick, last_asked = 0, 0, None
    grip = 0.0
    while True:
        if last_asked is None or index - last_asked >= cfg.h_min:  # the mirror's usefulness rule
            pending.append((tick + cfg.latency_ticks, index, chunk_of()))
            last_asked = index
        for arrival, start, actions in [p for p in pending if p[0] <= tick]:
            buffer.add(start, start, actions, float(arrival))
        pending = [p for p in pending if p[0] > tick]
        action = buffer.action_for(index)
        if action is None:
            action = np.array([0.0, 0.0, 0.0, grip])  # starved: the arm holds
        else:
            index += 1
            grip = float(action[3])
        tick += 1
        if task.step(action).done:
            return


def run_served(cfg: TasksConfig, work: Path, episode_boundaries: bool = True) -> dict[str, Any]:
    """The checkpoint(s) served to ``cfg.robots`` MetaWorld robots over the real protocol."""
    tasks, paths = cfg.tasks, cfg.policy_paths
    run_dir = work / f"{'+'.join(tasks)}-N{cfg.robots}-{cfg.scheduler}-{cfg.emulate_profile or 'cpu'}-h{cfg.h_min}-{cfg.h_max}"
    (run_dir / "stats").mkdir(parents=True, exist_ok=True)
    batch_log = run_dir / "batches.jsonl"
    args = [
        "--policy.device=cpu", "--port=0", f"--scheduler.type={cfg.scheduler}", f"--max_batch_size={cfg.max_batch_size}",
        f"--batch_log={batch_log}", "--status_interval_s=0", "--log_level=warning", *shlex.split(cfg.server_args),
    ]  # fmt: skip
    if len(tasks) > 1:
        (run_dir / "policies.json").write_text(json.dumps({t: {"path": paths[t]} for t in tasks}))
        args.append(f"--policies={run_dir / 'policies.json'}")
    else:
        args.append(f"--policy.path={paths[tasks[0]]}")
    specs = []
    for k in range(cfg.robots):
        task = tasks[k % len(tasks)]
        fast = TASKS[task].kind == "dynamic"
        specs.append({
            "robot_id": f"{task}-{k}", "tier": "fast" if fast else "slow", "task": task,
            "policy_name": task if len(tasks) > 1 else "", "fps": cfg.fps, "h_min": cfg.h_min, "h_max": cfg.h_max,
            "weight": cfg.fast_weight if fast else 1.0, "seed": cfg.seed + k * (cfg.episodes or 1000),
            "episodes": cfg.episodes,
        })  # fmt: skip
    if any(s["weight"] != 1.0 for s in specs):  # the operator grants the weights the fast robots ask for
        (run_dir / "grant_rules.json").write_text(
            json.dumps({"robots": {s["robot_id"]: {"max_weight": s["weight"]} for s in specs if s["weight"] != 1.0}})
        )
        args.append(f"--fleet.rules={run_dir / 'grant_rules.json'}")
    if cfg.emulate_profile:
        args.append(f"--engine.emulate_profile={cfg.emulate_profile}")
    server, address = start_server(args)
    groups = max(1, min(cfg.groups, cfg.robots))
    limit_s = cfg.duration_s or cfg.max_minutes * 60.0
    procs = []
    t0 = time.monotonic()
    try:
        for g in range(groups):
            spec = run_dir / f"group{g}.json"
            spec.write_text(json.dumps({
                "kind": "metaworld", "address": address, "duration_s": limit_s, "stats_dir": str(run_dir / "stats"),
                "robots": [s for k, s in enumerate(specs) if k % groups == g], "net_median_ms": 0.0, "net_sigma": 0.0,
                "image_size": 0, "no_episode_boundaries": not episode_boundaries,
            }))  # fmt: skip
            procs.append(subprocess.Popen([sys.executable, "-m", "lerobot_armory.bench.robots", str(spec)]))
        codes = [p.wait(timeout=limit_s + 120) for p in procs]
    finally:
        stop_all(server, procs)
    if any(codes):
        raise RuntimeError(f"robot group(s) failed with exit codes {codes}; see the messages above")
    wall = time.monotonic() - t0
    stats = [json.loads(p.read_text()) for p in sorted((run_dir / "stats").glob("*.json"))]
    batches = [json.loads(line) for line in batch_log.read_text().splitlines() if line.strip()]
    per_robot = []
    for s in stats:
        minutes = s["ticks"] / s["fps"] / 60.0
        s["successes_per_min"] = s["successes"] / minutes if minutes else 0.0
        per_robot.append(s)
    episodes = sum(s["episodes_done"] for s in stats)
    wins = sum(s["successes"] for s in stats)
    sizes: dict[str, int] = {}
    for b in batches:
        sizes[str(len(b["robots"]))] = sizes.get(str(len(b["robots"])), 0) + 1
    tiers = {}
    for tier in ("fast", "slow"):
        rows = [s for s in stats if s["tier"] == tier]
        if rows:
            n, w = sum(r["episodes_done"] for r in rows), sum(r["successes"] for r in rows)
            tiers[tier] = {
                "robots": len(rows), "episodes": n, "successes": w, "success_rate": w / n if n else 0.0,
                "interval95": wilson(w, n), "successes_per_min_per_robot": float(np.mean([r["successes_per_min"] for r in rows])),
                "starvation_pct": float(np.mean([r["starvation_pct"] for r in rows])),
            }  # fmt: skip
    return {
        "mode": "served",
        "tiers": tiers,
        "scheduler": cfg.scheduler,
        "emulate_profile": cfg.emulate_profile,
        "h_min": cfg.h_min,
        "h_max": cfg.h_max,
        "episode_boundaries": episode_boundaries,
        "robots": cfg.robots,
        "episodes": episodes,
        "successes": wins,
        "success_rate": wins / episodes if episodes else 0.0,
        "interval95": wilson(wins, episodes),
        "successes_per_min": float(sum(s["successes_per_min"] for s in stats)),
        "successes_per_min_per_robot": float(np.mean([s["successes_per_min"] for s in stats])),
        "starvation_pct": float(np.mean([s["starvation_pct"] for s in stats])),
        "stale_episode_chunks": int(sum(s.get("stale_episode_chunks", 0) for s in stats)),
        "batch_sizes": dict(sorted(sizes.items(), key=lambda kv: int(kv[0]))),
        "wall_s": wall,
        "per_robot": per_robot,
    }


# ---- openpi: the server's openpi endpoint, asked as openpi's client asks ---------------------


def run_openpi(cfg: TasksConfig) -> dict[str, Any]:
    """The checkpoint served by ``lerobot-armory-server --openpi.port`` to one openpi-protocol
    client that evaluates it as openpi's LIBERO example does: one ``infer`` per ``h_min`` actions
    (``--openpi.replan_steps``), the simulator waiting for each answer; the same seeds as ``local``.

    The client speaks openpi's wire (websocket, msgpack frames, the server's metadata first) with
    the observation keys openpi's examples use (``observation/state``, ...), so the run covers the
    endpoint's key mapping, its codec and its mirror bookkeeping, not only the policy."""
    from websockets.sync.client import connect

    from lerobot_armory.entrypoints.openpi.codec import pack, unpack
    from lerobot_armory.robot.metaworld.tasks import MetaWorldTask

    path = cfg.policy_paths[cfg.tasks[0]]
    server, _ = start_server([
        f"--policy.path={path}", "--policy.device=cpu", "--port=0", "--max_batch_size=1", "--status_interval_s=0",
        "--log_level=warning", "--openpi.port=0", f"--openpi.fps={cfg.fps}", f"--openpi.replan_steps={cfg.h_min}",
        *shlex.split(cfg.server_args),
    ])  # fmt: skip
    task = None
    try:
        url = _openpi_url(server)
        task = MetaWorldTask(cfg.tasks[0])
        results = []
        t0 = time.monotonic()
        total = cfg.robots * cfg.episodes
        with connect(url, max_size=OPENPI_MAX_BYTES, compression=None, open_timeout=30) as ws:
            unpack(ws.recv(timeout=30), OPENPI_MAX_BYTES)  # the server's metadata, sent first

            def infer(obs: dict[str, Any]) -> np.ndarray:
                ws.send(pack(obs))
                reply = ws.recv(timeout=60)
                if isinstance(reply, str):  # openpi's server answers an error as a text frame
                    raise RuntimeError(f"the openpi endpoint refused the observation: {reply}")
                return np.asarray(unpack(reply, OPENPI_MAX_BYTES)["actions"])

            for k in range(total):
                seed = cfg.seed + k
                task.reset(seed)
                done = False
                while not done:
                    actions = infer({
                        "observation/state": task.agent_state().astype(np.float32),
                        "observation/environment_state": task.environment_state().astype(np.float32),
                        "prompt": task.spec.description,
                    })  # fmt: skip
                    for action in actions[: cfg.h_min]:
                        if done := task.step(action).done:
                            break
                results.append({"seed": seed, "success": bool(task.success), "ticks": task.ticks})
                _progress("openpi", results, total, t0)
    finally:
        if task is not None:
            task.close()
        stop_all(server, [])
    return episode_summary("openpi", results, replan_steps=cfg.h_min)


def _openpi_url(server: subprocess.Popen) -> str:
    """The openpi endpoint's address, from the start-up summary the server prints after it listens."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and server.stdout is not None:
        line = server.stdout.readline()
        if not line:
            break
        if "openpi clients:" in line:
            return line.split("openpi clients:")[1].split()[0]
    raise RuntimeError("the server printed no openpi endpoint address")


def robot_table(served: dict[str, Any]) -> str:
    """One row per robot, then the fleet."""
    header = f"{'robot':<16} {'episodes':>8} {'successes':>9} {'rate':>6} {'95% interval':>14} {'succ/min':>8} {'starved %':>9}"
    lines = [header, "-" * len(header)]
    for s in served["per_robot"]:
        lo, hi = wilson(s["successes"], s["episodes_done"])
        rate = s["successes"] / s["episodes_done"] if s["episodes_done"] else 0.0
        lines.append(
            f"{s['robot_id']:<16} {s['episodes_done']:>8} {s['successes']:>9} {rate:>6.2f} {f'{lo:.2f}-{hi:.2f}':>14} "
            f"{s['successes_per_min']:>8.2f} {s['starvation_pct']:>9.1f}"
        )
    lo, hi = served["interval95"]
    lines.append(
        f"{'fleet':<16} {served['episodes']:>8} {served['successes']:>9} {served['success_rate']:>6.2f} {f'{lo:.2f}-{hi:.2f}':>14} "
        f"{served['successes_per_min']:>8.2f} {served['starvation_pct']:>9.1f}"
    )
    return "\n".join(lines)


def run(cfg: TasksConfig) -> dict[str, Any]:
    """Run the modes asked for, print the tables, write JSON; returns the results."""
    cfg.validate()
    warnings.filterwarnings("ignore", message="Constant")  # MetaWorld's experts, if imported
    from lerobot_armory.robot.metaworld.tasks import _import_metaworld

    _import_metaworld()  # one line if the simulator is missing, before any server starts
    out: dict[str, Any] = {"command": "lerobot-armory-tasks " + " ".join(shlex.quote(a) for a in sys.argv[1:]), "task": cfg.task}
    kinds = ", ".join(f"{t} ({TASKS[t].kind})" for t in cfg.tasks)
    size = f"{cfg.robots * cfg.episodes} episodes" if cfg.episodes else f"{cfg.duration_s:g} s"
    print(f"task {kinds}, checkpoint {cfg.policy_path}, {cfg.robots} robot(s), {size}, seeds from {cfg.seed}")
    if cfg.mode in ("local", "both"):
        local = run_local(cfg)
        lo, hi = local["interval95"]
        print(f"local (LeRobot's select_action loop): {local['successes']}/{local['episodes']} = {local['success_rate']:.2f} [{lo:.2f}, {hi:.2f}]")
        out["local"] = local
    if cfg.mode in ("served", "both"):
        prof = cfg.emulate_profile or "the checkpoint's real timing on this CPU"
        print(f"served: {cfg.robots} metaworld robot(s) at {cfg.fps:g} Hz, h_min {cfg.h_min}, h_max {cfg.h_max}, {cfg.scheduler}, {prof}", flush=True)
        work = Path(tempfile.mkdtemp(prefix="armory-tasks-"))
        served = run_served(cfg, work)
        print(robot_table(served))
        out["served"] = served
    if cfg.mode == "openpi":
        openpi = run_openpi(cfg)
        lo, hi = openpi["interval95"]
        print(f"openpi endpoint (replan {cfg.h_min}): {openpi['successes']}/{openpi['episodes']} = {openpi['success_rate']:.2f} [{lo:.2f}, {hi:.2f}]")
        out["openpi"] = openpi
    if "local" in out and "served" in out:
        lo, hi = out["local"]["interval95"]
        inside = lo <= out["served"]["success_rate"] <= hi
        out["anchor_holds"] = inside
        print(
            f"anchor: served {out['served']['success_rate']:.2f} is {'inside' if inside else 'OUTSIDE'} "
            f"local's 95 % interval [{lo:.2f}, {hi:.2f}]"
        )
    if cfg.output:
        Path(cfg.output).parent.mkdir(parents=True, exist_ok=True)
        Path(cfg.output).write_text(json.dumps(out, indent=2, default=float) + "\n")
        print(f"wrote {cfg.output}")
    return out


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    cfg = parse_or_exit(TasksConfig, argv, "lerobot-armory-tasks")
    run_or_exit(run, cfg, "lerobot-armory-tasks")


if __name__ == "__main__":
    main()

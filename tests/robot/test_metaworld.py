"""The metaworld robot: a real MuJoCo simulator stepped once per control tick, holding when starved."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("metaworld", reason="the metaworld extra (metaworld==3.0.0, mujoco==3.3.2) is not installed")

from lerobot_armory.robot.features import ENV_STATE, STATE, FeatureMap  # noqa: E402
from lerobot_armory.robot.metaworld import MetaWorldRobot, MetaWorldRobotConfig  # noqa: E402
from lerobot_armory.robot.metaworld.tasks import TASKS, MetaWorldTask, SimulatorUnavailable  # noqa: E402


def test_features_split_robot_state_from_the_worlds_state():
    robot = MetaWorldRobot(MetaWorldRobotConfig(task="push"))
    robot.connect()
    try:
        fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
        assert fmap.wire_features() == {STATE: ("float32", (4,)), ENV_STATE: ("float32", (39,))}
        wire = fmap.to_wire(robot.get_observation())
        np.testing.assert_allclose(wire[ENV_STATE][:4], wire[STATE])  # the hand and gripper lead MetaWorld's state
        assert fmap.action_keys == ("dx", "dy", "dz", "grip")
    finally:
        robot.disconnect()


def test_a_starved_tick_still_steps_the_world_with_the_arm_held():
    robot = MetaWorldRobot(MetaWorldRobotConfig(task="reach-moving"))
    robot.connect()
    try:
        first = robot.get_observation()
        goal0 = [first[f"environment_state.{k}"] for k in (36, 37, 38)]
        robot.send_action({"dx": 1.0, "dy": 0.0, "dz": 0.0, "grip": 0.0})
        robot.get_observation()
        assert robot.task.ticks == 1
        # No action this tick (starved): the next observation steps the world once, the arm held.
        held = robot.get_observation()
        assert robot.task.ticks == 2
        hand = np.array([held["hand.x"], held["hand.y"], held["hand.z"]])
        again = robot.get_observation()
        assert robot.task.ticks == 3
        assert np.linalg.norm(np.array([again["hand.x"], again["hand.y"], again["hand.z"]]) - hand) < 0.003
        goal3 = [again[f"environment_state.{k}"] for k in (36, 37, 38)]
        assert np.linalg.norm(np.subtract(goal3, goal0)) > 0.005, "the dynamic target did not move while the arm held"
    finally:
        robot.disconnect()


def test_a_loop_that_observes_only_some_ticks_steps_the_world_once_per_tick():
    # LeRobot's async robot_client observes only when its queue runs low; on a tick without an
    # action it calls hold(). Every tick is one physics step, however acting and observing mix.
    robot = MetaWorldRobot(MetaWorldRobotConfig(task="push"))
    robot.connect()
    try:
        act = {"dx": 0.0, "dy": 0.0, "dz": 0.0, "grip": 0.0}
        robot.get_observation()
        robot.send_action(act)  # tick 1: acted and observed
        robot.get_observation()
        robot.send_action(act)  # tick 2: acted, not observed
        robot.hold()  # tick 3: starved, then observed
        robot.get_observation()
        robot.hold()  # tick 4: starved, observed
        robot.get_observation()
        robot.send_action(act)  # tick 5
        assert robot.task.ticks == 5
    finally:
        robot.disconnect()


@pytest.mark.slow
def test_episodes_end_at_the_time_limit_and_restart_with_the_next_seed():
    limit = TASKS["push"].max_ticks
    robot = MetaWorldRobot(MetaWorldRobotConfig(task="push", seed=1234, episodes=2))
    robot.connect()
    try:
        for _ in range(2 * limit + 5):
            robot.get_observation()  # never acts: holds at the start until the time limit
        assert robot.finished and robot.episode == 1
        assert [(r["seed"], r["success"], r["ticks"]) for r in robot.results] == [(1234, False, limit), (1235, False, limit)]
        assert robot.task_stats()["success_rate"] == 0.0
    finally:
        robot.disconnect()


@pytest.mark.slow
def test_the_scripted_experts_solve_both_tasks_from_the_live_state():
    for name in TASKS:
        task = MetaWorldTask(name)
        wins = 0
        for seed in range(1000, 1004):
            task.reset(seed)
            while not task.step(task.expert_action()).done:
                pass
            wins += task.success
        task.close()
        assert wins == 4, name


@pytest.mark.slow
def test_a_layout_is_drawn_from_the_seed_alone():
    a, b = MetaWorldTask("reach-moving"), MetaWorldTask("reach-moving")
    a.reset(1001)
    b.reset(7)
    b.reset(1001)
    np.testing.assert_array_equal(a.environment_state(), b.environment_state())
    a.reset(1002)
    assert not np.array_equal(a.environment_state(), b.environment_state())


def test_a_bad_action_is_refused_in_one_line():
    robot = MetaWorldRobot(MetaWorldRobotConfig())
    robot.connect()
    try:
        with pytest.raises(ValueError, match="NaN or inf"):
            robot.send_action({"dx": float("nan"), "dy": 0.0, "dz": 0.0, "grip": 0.0})
    finally:
        robot.disconnect()


@pytest.mark.parametrize(
    ("argv", "env", "expected"),
    [
        (["--robot.task=pick"], {}, "robot.task: unknown MetaWorld task 'pick': known tasks are push, reach-moving"),
        (["--robot.image_size=64"], {"MUJOCO_GL": "bogus"}, "robot metaworld: MuJoCo cannot start: RuntimeError: invalid value"),
    ],
)
@pytest.mark.slow
@pytest.mark.subprocess
def test_bad_inputs_are_one_clear_line(argv, env, expected):
    import os

    out = subprocess.run(
        [sys.executable, "-m", "lerobot_armory.robot.cli", "--robot.type=metaworld", "--server_address=127.0.0.1:1", *argv],
        capture_output=True, text=True, timeout=120, env={**os.environ, **env},
    )  # fmt: skip
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("lerobot-armory-client")]
    assert out.returncode in (1, 2) and len(lines) == 1 and expected in lines[0], out.stderr[-2000:]


def test_a_missing_simulator_is_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "metaworld", None)  # import metaworld now raises ImportError
    with pytest.raises(SimulatorUnavailable, match=r"needs MetaWorld: pip install 'lerobot-armory\[metaworld\]'"):
        MetaWorldTask("push")

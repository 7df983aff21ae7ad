"""Each robot's observation history, as the fleet keeps it for policies with ``n_obs_steps > 1``."""

from __future__ import annotations

import numpy as np

from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.serving.fleet import Fleet


def obs(value: float) -> dict[str, np.ndarray]:
    return {"observation.state": np.full(2, value, np.float32)}


def values(history) -> list[float]:
    return [float(o["observation.state"][0]) for o in history]


def fleet_with(history_steps: int):
    now = [0.0]
    fleet = Fleet(lambda: now[0], history_steps=history_steps)
    a = fleet.register(RobotSpec("a", 20.0, 20, 1, 10), "", {})
    b = fleet.register(RobotSpec("b", 20.0, 20, 1, 10), "", {})
    return fleet, a, b, now


def test_each_robot_keeps_its_own_last_observations_by_tick():
    fleet, a, b, now = fleet_with(3)
    for k in range(5):
        now[0] = 0.05 * k
        fleet.on_observation(a, k, now[0], obs(k), now[0])
        fleet.on_observation(b, k, now[0], obs(100 + k), now[0])
    assert values(a.history(3)) == [2, 3, 4]
    assert values(b.history(3)) == [102, 103, 104]
    assert len(a.recent) == 3  # bounded: only what one row needs


def test_a_fresh_robot_repeats_its_first_observation_as_lerobot_fills_a_new_episode():
    fleet, a, _, _ = fleet_with(3)
    fleet.on_observation(a, 0, 0.0, obs(7), 0.0)
    assert values(a.history(3)) == [7, 7, 7]
    fleet.on_observation(a, 1, 0.05, obs(8), 0.05)
    assert values(a.history(3)) == [7, 7, 8]


def test_a_tick_without_an_observation_holds_the_previous_one():
    fleet, a, _, _ = fleet_with(3)
    fleet.on_observation(a, 4, 0.0, obs(4), 0.0)
    fleet.on_observation(a, 6, 0.1, obs(6), 0.1)  # tick 5 was lost
    assert values(a.history(3)) == [4, 4, 6]


def test_a_resent_tick_replaces_its_own_observation_and_keeps_the_earlier_ticks():
    fleet, a, _, _ = fleet_with(2)
    fleet.on_observation(a, 3, 0.0, obs(3), 0.0)
    fleet.on_observation(a, 4, 0.05, obs(4.0), 0.05)
    fleet.on_observation(a, 4, 0.06, obs(4.5), 0.06)  # a robot waiting for actions sends its tick again
    fleet.on_observation(a, 4, 0.07, obs(4.75), 0.07)
    assert values(a.history(2)) == [3, 4.75]


def test_without_a_history_policy_nothing_is_kept():
    fleet, a, _, _ = fleet_with(1)
    fleet.on_observation(a, 0, 0.0, obs(1), 0.0)
    assert a.recent is None and values(a.history(1)) == [1]

"""One validator for what a robot declares (``mirror.spec_problems``), used by ``RobotSpec``, by
the server's registration and by the client's command line: each names every problem at once."""

from __future__ import annotations

import math

import grpc
import pytest

from tests.support.echo import FEATURES, echo_server
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import MAX_ROBOT_ID, TIERS, RobotSpec, spec_problems
from lerobot_armory.robot.armory_sim import ArmorySimConfig
from lerobot_armory.robot.cli import ClientConfig
from lerobot_armory.robot.connection import Connection

# Three bad fields at once: a robot that cannot tick, a negative importance, an unknown tier.
BAD = dict(fps=0.0, weight=-1.0, tier="turbo")


def fields(problems: list[str]) -> list[str]:
    return [p.partition(": ")[0] for p in problems]


def test_a_valid_spec_has_no_problems():
    assert spec_problems("arm-1", 30.0, 50, 2, 10, 3.0, "fast") == []
    assert spec_problems("arm-1", 30.0, None, 0, 100, 1.0, "slow") == []  # H unknown: h_max unbounded


def test_every_problem_is_named_once_as_field_colon_why():
    problems = spec_problems("a", 0.0, 10, 1, 6, -1.0, "turbo")
    assert fields(problems) == ["fps", "weight", "tier"]
    assert "must be a number of steps per second in [0.01, 1000], got 0.0" in problems[0]
    assert "must be a positive number" in problems[1]
    assert f"must be one of {', '.join(TIERS)}, got 'turbo'" in problems[2]
    # A relation is checked only between fields that are valid on their own: h_max = 0 is named
    # once, not again as "h_min is larger than h_max".
    assert fields(spec_problems("a", 20.0, 10, 3, 0, 1.0, "slow")) == ["h_max"]
    assert fields(spec_problems("a", 20.0, 10, 7, 6, 1.0, "slow")) == ["h_min"]
    assert fields(spec_problems("a", 20.0, 10, 1, 11, 1.0, "slow")) == ["h_max"]


def test_values_of_the_wrong_type_are_problems_not_exceptions():
    problems = spec_problems(None, "fast", 10.5, 1.5, True, math.nan, ["slow"])  # type: ignore[arg-type]
    assert fields(problems) == ["robot_id", "fps", "chunk_size", "h_min", "h_max", "weight", "tier"]
    long_id = "x" * (MAX_ROBOT_ID + 1)
    assert fields(spec_problems(long_id, 20.0, 10, 1, 6, 1.0, "slow")) == ["robot_id"]
    assert fields(spec_problems("bell\x07", 20.0, 10, 1, 6, 1.0, "slow")) == ["robot_id"]
    # An echoed value from the wire is cut short.
    assert len(spec_problems("a", 20.0, 10, 1, 6, 1.0, "t" * 10_000)[0]) < 120


def test_robot_spec_raises_one_error_naming_all_three_fields():
    with pytest.raises(ConfigError) as info:
        RobotSpec("a", chunk_size=10, h_min=1, h_max=6, **BAD)
    text = str(info.value)
    assert info.value.field == "fps" and text.startswith("fps: ")
    for name in ("fps", "weight", "tier"):
        assert f"{name}: " in text, text
    assert text == "; ".join(spec_problems("a", 0.0, 10, 1, 6, -1.0, "turbo"))


def test_a_server_registration_with_three_bad_fields_names_all_three():
    server = echo_server()
    conn = Connection(server.address)
    try:
        with pytest.raises(grpc.RpcError) as info:
            conn.register("bad-arm", FEATURES, fps=BAD["fps"], h_min=1, h_max=6, weight=BAD["weight"], tier=BAD["tier"])
        assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        details = info.value.details()
        # The very texts of the shared validator, all in one answer (the policy's H is 10).
        for problem in spec_problems("bad-arm", 0.0, 10, 1, 6, -1.0, "turbo"):
            assert problem in details, f"{problem!r} not in {details!r}"
        # h_max above the policy's chunk size is judged against the policy, not the robot.
        with pytest.raises(grpc.RpcError) as info:
            conn.register("long-arm", FEATURES, fps=20.0, h_min=1, h_max=11)
        assert "h_max: h_max=11 is larger than the chunk size H=10" in info.value.details()
    finally:
        conn.close()
        server.stop(0.5)


def test_the_client_config_names_every_problem_of_the_command_line():
    cfg = ClientConfig(robot=ArmorySimConfig(), robot_id="arm", duration_s=-1.0, log_level="loud", **BAD)
    with pytest.raises(ConfigError) as info:
        cfg.validate()
    text = str(info.value)
    for problem in spec_problems("arm", 0.0, None, cfg.h_min, cfg.h_max, -1.0, "turbo"):
        assert problem in text, text
    assert "duration_s: must be >= 0" in text and "log_level: must be one of" in text
    # The client does not know the policy's chunk size: a large h_max is the server's to judge.
    ClientConfig(robot=ArmorySimConfig(), robot_id="arm", h_max=500).validate()


def test_the_client_command_prints_every_problem_on_one_line(capsys):
    from lerobot_armory.robot.cli import main

    with pytest.raises(SystemExit) as info:
        main(["--robot.type=armory_sim", "--robot_id=arm", "--fps=0", "--weight=-1", "--tier=turbo"])
    assert info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    for name in ("fps: ", "weight: ", "tier: "):
        assert name in lines[0], lines[0]

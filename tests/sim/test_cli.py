"""``lerobot-armory-sim`` in-process: JSON output, the table, both argument forms, one-line errors."""

from __future__ import annotations

import json

import pytest

from lerobot_armory.sim.cli import main

DOCUMENTED_KEYS = {
    "scheduler",
    "mix",
    "robots",
    "seed",
    "max_batch_size",
    "fast_weight",
    "avg_starvation_pct",
    "tiers",
    "batch_sizes",
    "decision_ms_p99",
}
TIMING_KEYS = {"wall_s", "decision_ms_p50", "decision_ms_p99", "decision_cpu_ms_p50", "decision_cpu_ms_p99"}


def run_cli(args, tmp_path, name="out.json"):
    out = tmp_path / name
    main([*args, f"--output={out}"])
    return json.loads(out.read_text())


def test_json_has_the_documented_keys_and_the_table_is_printed(capsys, tmp_path):
    data = run_cli(["--duration_s=3", "--robots=4", "--scheduler.type=edf"], tmp_path)
    assert set(data) == {"runs"}
    (run,) = data["runs"]
    assert DOCUMENTED_KEYS <= set(run)
    assert run["scheduler"] == "edf"
    assert run["mix"] == "one-fast" and run["robots"] == 4 and run["seed"] == 0
    assert run["max_batch_size"] == 3 and run["fast_weight"] == 1.0
    assert set(run["tiers"]) == {"fast", "slow"}
    assert run["tiers"]["fast"]["robots"] == 1 and run["tiers"]["slow"]["robots"] == 3
    assert 0.0 <= run["avg_starvation_pct"] <= 100.0
    assert run["batch_sizes"] and all(1 <= int(b) <= 3 and c > 0 for b, c in run["batch_sizes"].items())
    assert run["decision_ms_p99"] >= 0.0
    out = capsys.readouterr().out
    lines = out.splitlines()
    header = next(line for line in lines if line.startswith("preset"))
    for column in ("scheduler", "fast starv%", "slow starv%", "avg starv%"):
        assert column in header
    row = next(line for line in lines if line.startswith("libero"))
    assert "EDF" in row and "one-fast" in row
    assert f"{run['avg_starvation_pct']:.2f}" in row
    assert "wrote 1 runs" in out


def test_seeds_run_consecutively(capsys, tmp_path):
    data = run_cli(["--duration_s=2", "--robots=3", "--scheduler.type=rr", "--seeds=3", "--seed=5"], tmp_path)
    assert [r["seed"] for r in data["runs"]] == [5, 6, 7]
    err = capsys.readouterr().err
    assert "[1/3] seed=5" in err and "[3/3] seed=7" in err


def test_output_directory_is_created(tmp_path):
    data = run_cli(["--duration_s=1", "--robots=2"], tmp_path, name="deep/er/out.json")
    assert len(data["runs"]) == 1


def test_space_separated_and_equals_forms_agree(capsys, tmp_path):
    common = ["--duration_s=3"]
    eq = run_cli(
        ["--preset=piper", "--mix=half-fast", "--robots=4", "--scheduler.type=lookahead", "--fast_weight=3", *common],
        tmp_path,
        "eq.json",
    )["runs"][0]
    sp = run_cli(
        ["--preset", "piper", "--mix", "half-fast", "--robots", "4", "--scheduler.type", "lookahead", "--fast_weight", "3", *common],
        tmp_path,
        "sp.json",
    )["runs"][0]
    assert eq["preset"] == sp["preset"] == "piper"
    assert eq["mix"] == "half-fast" and eq["robots"] == 4 and eq["fast_weight"] == 3.0
    assert eq["max_batch_size"] == 5  # piper's cap for mixed fleets
    assert {k: v for k, v in eq.items() if k not in TIMING_KEYS} == {k: v for k, v in sp.items() if k not in TIMING_KEYS}


def test_preset_libero_space_form(tmp_path):
    run = run_cli(["--preset", "libero", "--duration_s", "2", "--robots", "2"], tmp_path)["runs"][0]
    assert run["preset"] == "libero" and run["duration_s"] == 2.0


def test_depth_reaches_the_record(tmp_path):
    run = run_cli(["--scheduler.type=lookahead", "--scheduler.depth=2", "--duration_s=2", "--robots=3"], tmp_path)["runs"][0]
    assert run["depth"] == 2
    assert run["label"] == "LA w=1 L=2"


def test_extrapolated_cap_is_announced(capsys, tmp_path):
    run = run_cli(["--mix=all-fast", "--robots=8", "--max_batch_size=7", "--duration_s=2"], tmp_path)["runs"][0]
    assert run["latency_extrapolated"] is True
    assert "extrapolated" in capsys.readouterr().err


def test_help_exits_zero(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code in (0, None)
    assert "--scheduler.type" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------
# Bad input: exit code 2, one line on stderr naming the field, no traceback


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


BAD_INPUTS = [
    (["--robots=0"], "robots"),
    (["--robots=abc"], "robots"),
    (["--max_batch_size=0"], "max_batch_size"),
    (["--preset=nope"], "preset"),
    (["--mix=nope"], "mix"),
    (["--latency_profile=/nonexistent.json"], "latency_profile"),
    (["--latency_profile=nope-gpu"], "latency_profile"),
    (["--duration_s=0"], "duration_s"),
    (["--duration_s=-5"], "duration_s"),
    (["--seeds=0"], "seeds"),
    (["--scheduler.type=lookahead", "--scheduler.depth=0"], "scheduler.depth"),
    (["--scheduler.type", "lookahead", "--scheduler.depth", "0"], "scheduler.depth"),
    (["--scheduler.type=lookahead", "--scheduler.window_s=0"], "scheduler.window_s"),
    (["--fast_weight=0"], "fast_weight"),
    (["--fast_weight=-2"], "fast_weight"),
    (["--net_sigma=-1"], "net_sigma"),
    (["--net_median_ms=-5"], "net_median_ms"),
]


def check_one_line_error(capsys, args, field):
    with pytest.raises(SystemExit) as info:
        main([*args, "--duration_s=1"] if not any(a.startswith("--duration_s") for a in args) else args)
    assert info.value.code == 2
    captured = capsys.readouterr()
    err_lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "Traceback" not in captured.err and "Traceback" not in captured.out
    assert err_lines, "an error message is expected on stderr"
    assert field in err_lines[-1]
    assert "error" in err_lines[-1]
    return err_lines


@pytest.mark.parametrize("args, field", BAD_INPUTS)
def test_bad_input_one_line_naming_the_field(capsys, args, field):
    err_lines = check_one_line_error(capsys, args, field)
    assert len(err_lines) == 1, err_lines


@pytest.mark.parametrize(
    "content",
    ['{"latency_ms": [73.0, 109.8', '{"latency_ms": [5, 4]}', '{"latency_ms": [10, -1]}', '{"latency_ms": {"1": 1, "3": 3}}'],
    ids=["malformed", "decreasing", "negative", "gap"],
)
def test_bad_profile_files(capsys, tmp_path, content):
    path = write(tmp_path, "p.json", content)
    err_lines = check_one_line_error(capsys, [f"--latency_profile={path}"], "latency_profile")
    assert len(err_lines) == 1


def test_good_profile_file(tmp_path):
    path = write(tmp_path, "p.json", '{"name": "tiny", "latency_ms": {"1": 20, "2": 30}}')
    run = run_cli([f"--latency_profile={path}", "--max_batch_size=2", "--duration_s=2", "--robots=3"], tmp_path)["runs"][0]
    assert run["latency_profile"] == path
    assert run["latency_extrapolated"] is False


def test_unknown_scheduler_exits_2_naming_the_field(capsys):
    check_one_line_error(capsys, ["--scheduler.type=nope"], "scheduler.type")


def test_unknown_option_exits_2(capsys):
    check_one_line_error(capsys, ["--bogus=1"], "bogus")


@pytest.mark.parametrize("args, field", [(["--scheduler.type=nope"], "scheduler.type"), (["--bogus=1"], "bogus")])
def test_argparse_errors_are_one_line(capsys, args, field):
    err_lines = check_one_line_error(capsys, args, field)
    assert len(err_lines) == 1, err_lines


@pytest.mark.parametrize("args, field", [(["--scheduler.depth=0"], "scheduler.depth"), (["--scheduler.window_s=0"], "scheduler.window_s")])
def test_knob_errors_without_explicit_type_name_the_knob(capsys, args, field):
    check_one_line_error(capsys, args, field)


def test_knob_for_the_default_scheduler_without_type(tmp_path):
    run = run_cli(["--scheduler.depth=2", "--duration_s=1", "--robots=2"], tmp_path)["runs"][0]
    assert run["depth"] == 2


def test_dict_profile_with_leading_zero_keys_never_tracebacks(capsys, tmp_path):
    path = write(tmp_path, "p.json", '{"latency_ms": {"01": 42.3, "02": 56.0}}')
    try:
        main([f"--latency_profile={path}", "--duration_s=1", "--robots=2", "--max_batch_size=2"])
    except SystemExit as exc:
        assert exc.code == 2
        assert "latency_profile" in capsys.readouterr().err

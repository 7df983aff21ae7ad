"""Latency profiles d_infer(b): built-in tables (SPEC §5), extrapolation, JSON files, errors."""

from __future__ import annotations

import json

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.latency import BUILTIN_PROFILES, LatencyProfile, load_profile

SPEC_TABLES = {
    "l40s-pi05": [73.0, 109.8, 142.4, 177.5, 211.1],
    "h100-pi05": [42.3, 56.0, 66.1, 79.3, 87.2],
    "l40s-groot": [71.8, 76.5, 83.5, 91.8, 100.9],
}


@pytest.mark.parametrize("name", sorted(SPEC_TABLES))
def test_builtin_profiles_match_spec(name):
    p = load_profile(name)
    assert p.name == name
    assert p.source == "builtin"
    assert list(p.latency_ms) == SPEC_TABLES[name]
    assert p.measured_sizes == 5
    for b, ms in enumerate(SPEC_TABLES[name], start=1):
        assert p.latency_ms_for(b) == ms
        assert p.latency_s(b) == pytest.approx(ms / 1000)
        assert not p.is_extrapolated(b)


def test_builtin_names():
    assert set(BUILTIN_PROFILES) == set(SPEC_TABLES)
    assert "H100" in load_profile("h100-pi05").device


def test_linear_extrapolation_beyond_the_table():
    p = load_profile("l40s-pi05")
    assert p.latency_ms_for(6) == pytest.approx(211.1 + 33.6)
    assert p.latency_ms_for(8) == pytest.approx(211.1 + 3 * 33.6)
    assert p.is_extrapolated(6) and p.is_extrapolated(10)
    assert not p.is_extrapolated(5)
    h = load_profile("h100-pi05")
    assert h.latency_ms_for(7) == pytest.approx(87.2 + 2 * 7.9)


def test_table_s_and_describe_mark_extrapolation():
    p = load_profile("l40s-groot")
    table = p.table_s(7)
    assert table[:5] == pytest.approx([0.0718, 0.0765, 0.0835, 0.0918, 0.1009])
    assert table[5] == pytest.approx((100.9 + 9.1) / 1000)
    assert table[6] == pytest.approx((100.9 + 2 * 9.1) / 1000)
    text = p.describe(7)
    lines = text.splitlines()
    assert len(lines) == 1 + 7
    assert sum("extrapolated" in line for line in lines) == 2
    assert "extrapolated" not in lines[5] and "extrapolated" in lines[6]


def test_single_point_profile_assumes_no_batching_gain():
    p = LatencyProfile("one", (10.0,))
    assert p.latency_ms_for(3) == pytest.approx(30.0)
    assert p.is_extrapolated(2)


def test_batch_size_below_one_is_rejected():
    with pytest.raises(ValueError):
        load_profile("l40s-pi05").latency_ms_for(0)


def write(tmp_path, data, name="profile.json"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def test_load_list_form(tmp_path):
    path = write(tmp_path, {"name": "my-gpu", "device": "H100", "latency_ms": [42.3, 56.0, 66.1]})
    p = load_profile(path)
    assert p.name == "my-gpu"
    assert p.device == "H100"
    assert p.latency_ms == (42.3, 56.0, 66.1)
    assert p.source == path
    assert p.latency_ms_for(4) == pytest.approx(66.1 + 10.1)


def test_load_dict_form_in_any_key_order(tmp_path):
    path = write(tmp_path, {"latency_ms": {"3": 30, "1": 10, "2": 20.5}}, name="gpu-x.json")
    p = load_profile(path)
    assert p.latency_ms == (10.0, 20.5, 30.0)
    assert p.name == "gpu-x"  # no name: the file stem
    assert p.device == ""


def test_integer_entries_are_accepted_and_equal_entries_allowed(tmp_path):
    p = load_profile(write(tmp_path, {"latency_ms": [50, 50, 60]}))
    assert p.latency_ms == (50.0, 50.0, 60.0)


def test_save_load_round_trip(tmp_path):
    original = LatencyProfile("rt", (12.5, 20.0, 26.25), device="my box", source="profiled")
    path = tmp_path / "sub.json"
    original.save(path)
    assert json.loads(path.read_text()) == {"name": "rt", "device": "my box", "latency_ms": [12.5, 20.0, 26.25]}
    loaded = load_profile(str(path))
    assert (loaded.name, loaded.latency_ms, loaded.device) == (original.name, original.latency_ms, original.device)
    assert loaded.source == str(path)


def test_builtin_round_trip(tmp_path):
    path = tmp_path / "h100.json"
    load_profile("h100-pi05").save(path)
    assert load_profile(str(path)).latency_ms == tuple(SPEC_TABLES["h100-pi05"])


def assert_profile_error(path_or_name):
    with pytest.raises(ConfigError) as info:
        load_profile(path_or_name)
    assert info.value.field == "latency_profile"
    assert str(info.value).startswith("latency_profile: ")
    return info.value


def test_unknown_name():
    err = assert_profile_error("a100-pi05")
    assert "l40s-pi05" in err.message  # lists what would be accepted


def test_missing_file(tmp_path):
    assert_profile_error(str(tmp_path / "nonexistent.json"))
    assert_profile_error("/nonexistent.json")


def test_directory_is_not_a_profile(tmp_path):
    assert_profile_error(str(tmp_path))


@pytest.mark.parametrize(
    "content",
    [
        '{"latency_ms": [1, 2',  # malformed JSON
        "",  # empty file
        "[1, 2, 3]",  # not an object
        '{"latency": [1, 2]}',  # no latency_ms
        '{"latency_ms": "fast"}',  # neither list nor object
        '{"latency_ms": []}',  # empty table
        '{"latency_ms": [5, 4]}',  # decreasing
        '{"latency_ms": [10, 20, 15, 30]}',  # decreasing in the middle
        '{"latency_ms": [0, 1]}',  # non-positive
        '{"latency_ms": [-3]}',
        '{"latency_ms": [1, "a"]}',  # non-numeric
        '{"latency_ms": [1, null]}',
        '{"latency_ms": [1, true]}',
        '{"latency_ms": [1, NaN]}',
        '{"latency_ms": [1, Infinity]}',
        '{"latency_ms": {"1": 10, "3": 30}}',  # gap in batch sizes
        '{"latency_ms": {"2": 10, "3": 30}}',  # does not start at 1
        '{"latency_ms": {"one": 10}}',  # key not a batch size
        '{"latency_ms": {"1": 10, "2": 5}}',  # decreasing, dict form
        '{"latency_ms": {"1": 10, "2": "x"}}',  # non-numeric, dict form
    ],
)
def test_bad_files(tmp_path, content):
    assert_profile_error(write(tmp_path, content))


def test_non_utf8_file(tmp_path):
    path = tmp_path / "bin.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    assert_profile_error(str(path))


def test_dict_keys_with_leading_zero(tmp_path):
    path = write(tmp_path, {"latency_ms": {"01": 42.3, "02": 56.0}})
    try:
        p = load_profile(path)
    except ConfigError:
        return  # a clean ConfigError would also be acceptable
    assert p.latency_ms == (42.3, 56.0)


@pytest.mark.parametrize("values", [(), (0.0,), (-1.0, 2.0), (10.0, 9.0), (float("nan"),)])
def test_profile_object_validates_itself(values):
    with pytest.raises(ConfigError) as info:
        LatencyProfile("x", values)
    assert info.value.field == "latency_profile"

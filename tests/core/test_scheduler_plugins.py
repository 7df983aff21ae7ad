"""Schedulers from other installed packages: the entry-point group ``lerobot_armory.schedulers``."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import pytest

from lerobot_armory.inference_latency import load_profile
from lerobot_armory.schedulers import (
    ENTRY_POINT_GROUP,
    LookaheadConfig,
    Scheduler,
    SchedulerConfig,
    load_scheduler_plugins,
    make_scheduler_config,
    plugins,
    scheduler_names,
)

PLUGIN = '''
from dataclasses import dataclass

from lerobot_armory.schedulers import Scheduler, SchedulerConfig, useful


class FirstUseful(Scheduler):
    def select(self, robots, now):
        return useful(robots)[: self.max_batch_size]


@SchedulerConfig.register_subclass("myplug")
@dataclass
class MyPlugConfig(SchedulerConfig):
    knob: int = 3

    def build(self, profile, max_batch_size):
        return FirstUseful(profile, max_batch_size)
'''


def install(root: Path, dist: str, entry: str, module: str, source: str | None) -> None:
    """A distribution as pip leaves it in site-packages: NAME-VERSION.dist-info plus its module."""
    info = root / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{entry} = {module}\n")
    if source is not None:
        (root / f"{module}.py").write_text(source)


@pytest.fixture
def site(tmp_path, monkeypatch):
    """tmp_path on sys.path as a site-packages; what the plugins registered is forgotten afterwards."""
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(plugins, "_seen", set())
    monkeypatch.setattr(plugins, "_discovered", False)
    registry = SchedulerConfig._choice_registry
    before, modules = dict(registry), set(sys.modules)
    yield tmp_path
    registry.clear()
    registry.update(before)
    for name in set(sys.modules) - modules:
        if name.startswith(("myplug", "brokenplug")):
            del sys.modules[name]


def test_an_installed_plugin_registers_its_scheduler(site):
    install(site, "myplug", "myplug", "myplug_scheduler", PLUGIN)
    assert "myplug" not in SchedulerConfig._choice_registry
    assert load_scheduler_plugins() == ["myplug = myplug_scheduler"]
    assert "myplug" in scheduler_names()
    cfg = make_scheduler_config("myplug", knob=5)
    assert cfg.type == "myplug" and cfg.knob == 5
    assert isinstance(cfg.build(load_profile("l40s-pi05"), 3), Scheduler)
    assert load_scheduler_plugins() == []  # each entry point is loaded once


def test_the_registry_loads_plugins_on_first_use(site):
    """No explicit call: listing the schedulers, or parsing --scheduler.type, finds the plugin."""
    install(site, "myplug", "myplug", "myplug_scheduler", PLUGIN)
    assert "myplug" in scheduler_names()


def test_the_command_line_parses_a_plugin_scheduler(site):
    install(site, "myplug", "myplug", "myplug_scheduler", PLUGIN)

    @dataclass
    class Cfg:
        scheduler: SchedulerConfig = field(default_factory=LookaheadConfig)

    cfg = draccus.parse(Cfg, args=["--scheduler.type=myplug", "--scheduler.knob=7"])
    assert cfg.scheduler.type == "myplug" and cfg.scheduler.knob == 7


@pytest.mark.parametrize(
    ("source", "error"),
    [
        (None, "ModuleNotFoundError: No module named 'brokenplug_scheduler'"),
        ("raise RuntimeError('needs a GPU driver')", "RuntimeError: needs a GPU driver"),
        (PLUGIN.replace('"myplug"', '"edf"'), "ValueError"),  # a name already registered
    ],
    ids=["missing-module", "raises", "name-taken"],
)
def test_a_broken_plugin_warns_once_and_breaks_nothing(site, caplog, source, error):
    install(site, "brokenplug", "brokenplug", "brokenplug_scheduler", source)
    with caplog.at_level(logging.WARNING, logger=plugins.__name__):
        assert load_scheduler_plugins() == []
        names = scheduler_names()
    assert {"edf", "lookahead", "rr"} <= set(names)
    assert make_scheduler_config("edf").type == "edf"
    assert len(caplog.records) == 1, [r.getMessage() for r in caplog.records]
    line = caplog.records[0].getMessage()
    assert "brokenplug = brokenplug_scheduler" in line and "brokenplug 0.1" in line and error in line

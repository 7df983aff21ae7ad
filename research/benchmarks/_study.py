"""Helpers of the study benchmarks.

Puts ``research/`` (for :mod:`armory_research`) and the product's ``benchmarks/`` (for its
``_common`` helpers ``Targets`` and ``sim``, re-exported here) on ``sys.path``, and adds
:func:`play_episode`, which needs the study's deterministic episodes.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
for _path in (ROOT / "benchmarks", ROOT / "research"):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from _common import Targets, sim  # noqa: E402  (benchmarks/_common.py of the product)

from lerobot_armory.inference_latency import load_profile  # noqa: E402
from lerobot_armory.schedulers import make_scheduler_config  # noqa: E402
from lerobot_armory.sim.presets import get_preset  # noqa: E402

from armory_research.optimal import Episode, EpisodeResult, play  # noqa: E402

__all__ = ["Targets", "play_episode", "sim"]


def play_episode(preset: str, ep: Episode, scheduler: str, options: dict[str, object], tell_end: bool) -> EpisodeResult:
    """``scheduler`` (with ``options``, the preset's latency profile) on a deterministic episode."""
    profile = load_profile(get_preset(preset).latency_profile)
    return play(ep, make_scheduler_config(scheduler, **options).make(profile, ep.max_batch_size), tell_end=tell_end)

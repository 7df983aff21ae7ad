"""Shared builders for the tests: robots in hand-chosen states and a naive reference transition."""

from __future__ import annotations

from collections.abc import Sequence

from lerobot_armory.delay import DelayEstimator
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.transition import Chunk, TickChunk


def spec(
    robot_id: str = "r",
    fps: float = 10.0,
    chunk_size: int = 10,
    h_min: int = 1,
    h_max: int = 5,
    weight: float = 1.0,
    tier: str = "slow",
) -> RobotSpec:
    return RobotSpec(robot_id, fps, chunk_size, h_min, h_max, weight, tier)


def mirror(robot_id: str = "r", **kwargs) -> RobotMirror:
    """A mirror with a zero-delay estimator (server clock == robot clock, no network delay)."""
    return RobotMirror(spec(robot_id, **kwargs), DelayEstimator())


def served(m: RobotMirror, t_done: float) -> Chunk:
    """Dispatch the robot's latest observation in a batch that finishes (the chunk is sent) at
    ``t_done``: what the dispatcher's ``plan`` then ``complete`` do to one robot."""
    chunk = m.on_dispatch(t_done)
    m.on_complete(chunk, t_done)
    return chunk


def naive_run(index: int, chunks: Sequence[TickChunk], n_ticks: int):
    """Tick-by-tick reference of docs/spec.md §2's transition with the naive-async switch rule.

    Returns (final index, executed ticks, starved ticks, {position: first executed offset}).
    At every tick the newest arrived chunk covering the index (highest position in the list,
    which is sorted by i_start with older chunks first on ties) is the one executed.
    """
    i, executed, starved = index, 0, 0
    first_use: dict[int, int] = {}
    for tick in range(max(0, n_ticks)):
        covering = [p for p, (s, e, a) in enumerate(chunks) if a <= tick and s <= i < e]
        if covering:
            p = max(covering)
            first_use.setdefault(p, i - chunks[p][0])
            i += 1
            executed += 1
        else:
            starved += 1
    return i, executed, starved, first_use


def consistent_chunks(index: int, requests: Sequence[tuple[int, int, int]], n_ticks: int) -> list[TickChunk]:
    """Chunks a real robot could receive: request ``(obs_tick, delay_ticks, h)`` makes a chunk
    starting at the robot's index at ``obs_tick`` (observation sent before the tick's action)
    and arriving ``delay_ticks`` later. Built with the naive reference, in creation order."""
    by_tick: dict[int, list[tuple[int, int]]] = {}
    for obs_tick, delay, h in requests:
        by_tick.setdefault(obs_tick, []).append((delay, h))
    chunks: list[TickChunk] = []
    i = index
    for tick in range(n_ticks):
        for delay, h in by_tick.get(tick, []):
            chunks.append((i, i + h, tick + delay))
        if any(a <= tick and s <= i < e for s, e, a in chunks):
            i += 1
    return chunks

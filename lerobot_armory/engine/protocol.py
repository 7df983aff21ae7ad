"""What the serving loop needs from an engine: one protocol, every capability in it.

The loop calls these and nothing else; it never probes an engine's signature or attributes. An
engine that cannot guide chunks (no real-time chunking) says so with ``rtc = None``; the loop
then never calls :meth:`Engine.infer_guided`. Test doubles derive from :class:`UnguidedEngine`.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np


def noise_seed(robot_id: str, chunk_id: int) -> int:
    """The noise seed of one request: fixed by the robot and its chunk number, not by the batch.

    32 bits, because torch's CPU generator keeps only the low 32 bits of a seed (a seed that put
    the robot in the high bits would give every robot the same noise for the same chunk number).
    """
    return zlib.crc32(f"{chunk_id}:{robot_id}".encode())


class Engine(Protocol):
    """A batched policy: observations in, one action chunk per robot out.

    Attributes:
        rtc: the real-time chunking processor (:mod:`lerobot_armory.engine.rtc`), or None when
            the engine does not guide chunks by what each robot executes meanwhile.
        history_steps: consecutive observations the policy needs per row (its ``n_obs_steps``);
            above 1 the loop passes each robot's last ones as ``history``.
        unrecorded_batches: a running count of batches served without the CUDA graph meant for
            them (correct chunks, but at eager speed); 0 for an engine without graphs. The loop
            counts the batches during which it grew.
    """

    rtc: Any
    history_steps: int
    unrecorded_batches: int

    def infer(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None = None,
        history: Sequence[Sequence[dict[str, np.ndarray]]] | None = None,
    ) -> np.ndarray:
        """``(B, H, A)`` float32 chunks for ``B`` observations; ``noise_seeds`` (one per row, None:
        the engine's own) make a stochastic policy's chunk depend on its robot and chunk only;
        ``history[k]`` (only with ``history_steps > 1``) is row k's last observations, oldest first."""
        ...

    def infer_guided(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None,
        prefixes: Sequence[Any],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Chunks guided by each row's RTC prefix (None: unguided row): ``(actions, model_actions)``,
        the second in the policy's own action space (the next prefixes are cut from it)."""
        ...


class UnguidedEngine:
    """Base of engines without real-time chunking (test doubles, analytic policies): they define
    :meth:`Engine.infer` and inherit ``rtc = None``."""

    rtc: Any = None
    history_steps: int = 1
    unrecorded_batches: int = 0

    def infer_guided(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None,
        prefixes: Sequence[Any],
    ) -> tuple[np.ndarray, np.ndarray]:
        raise RuntimeError(f"{type(self).__name__} does not guide chunks (its rtc is None): the loop never asks it to")

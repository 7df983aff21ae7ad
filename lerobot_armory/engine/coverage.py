"""Is a LeRobot policy served batched, each robot's chunk as if alone? Measured on one directory.

:func:`check_policy` loads a policy directory the way ``--policy.path`` does and measures what
the coverage table (``docs/policies/coverage.md``, written by ``tests/policies/test_coverage.py``)
reports for it: refused or served, the chunk of three robots batched against each alone (their
own observation histories, prompts and noise, in two orders), what chance the chunk depends on,
per-robot prompts, RTC, the static sampler, and CPU latency.
"""

from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lerobot_armory.engine.protocol import noise_seed
from lerobot_armory.errors import ConfigError

TASKS = ("pick up the red block", "sort the bricks by colour", "reach the moving target")


@dataclass
class PolicyCheck:
    """What :func:`check_policy` measured for one policy directory.

    Attributes:
        type: LeRobot's ``config.type``.
        refusal: the one line the server refuses it with (None: served).
        chunk: ``(H, action_dim)`` of a served chunk.
        history: observations per row (``n_obs_steps``).
        randomness: what chance a chunk depends on (:mod:`lerobot_armory.engine.policy_kinds`).
        frozen: chance was frozen to compare batched with alone (it is drawn per batch).
        max_diff: largest |batched - alone| over every action of three robots, two orders.
        prompts: whether the prompt reaches the chunk.
        rtc: ``yes`` or why not.
        static_sampler: ``yes`` or why not.
        cpu_ms: batch size -> median milliseconds on this machine's CPU.
    """

    type: str
    refusal: str | None = None
    chunk: tuple[int, int] | None = None
    history: int = 1
    randomness: str = ""
    frozen: bool = False
    max_diff: float | None = None
    prompts: str = ""
    rtc: str = ""
    static_sampler: str = ""
    cpu_ms: dict[int, float] = field(default_factory=dict)


@contextlib.contextmanager
def frozen_chance() -> Iterator[None]:
    """torch's samplers made deterministic (normal draws 0, uniform 0.5, categorical argmax): a
    policy that draws for the whole batch can then be compared row by row with itself alone."""
    import torch

    saved = {name: getattr(torch, name) for name in ("randn", "randn_like", "rand", "rand_like", "multinomial")}

    def randn(*size: Any, generator: Any = None, **kw: Any) -> Any:
        return torch.zeros(*size, **kw)

    def rand(*size: Any, generator: Any = None, **kw: Any) -> Any:
        return torch.full(size[0] if len(size) == 1 and isinstance(size[0], (tuple, list, torch.Size)) else size, 0.5, **kw)

    try:
        torch.randn, torch.rand = randn, rand
        torch.randn_like = lambda t, **kw: torch.zeros_like(t, **{k: v for k, v in kw.items() if k != "generator"})
        torch.rand_like = lambda t, **kw: torch.full_like(t, 0.5, **{k: v for k, v in kw.items() if k != "generator"})
        torch.multinomial = lambda probs, num_samples, *a, **kw: probs.argmax(-1, keepdim=True).expand(
            *probs.shape[:-1], num_samples
        )
        yield
    finally:
        for name, fn in saved.items():
            setattr(torch, name, fn)


def check_policy(path: str, timing: bool = True) -> PolicyCheck:
    """Load ``path`` on the CPU and measure its row of the coverage table."""
    from lerobot_armory.engine import rtc as rtc_mod
    from lerobot_armory.engine.options import PolicyOptions
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.acceleration import static_sampler

    try:
        engine = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1))
    except ConfigError as exc:
        kind = _saved_type(path)
        return PolicyCheck(kind, refusal=str(exc))
    check = PolicyCheck(engine.config.type, chunk=(engine.chunk_size, engine.action_dim), history=engine.history_steps)
    check.randomness = engine.kind.randomness(engine.config)
    check.frozen = check.randomness.startswith("drawn per batch")
    steps = engine.history_steps
    histories = [[engine.example_observation(seed=10 * r + t) for t in range(steps)] for r in range(3)]
    current = [h[-1] for h in histories]
    seeds = [noise_seed(f"robot{r}", 5) for r in range(3)]
    hist = histories if steps > 1 else None
    with frozen_chance() if check.frozen else contextlib.nullcontext():
        together = engine.infer(current, list(TASKS), seeds, hist)
        diffs = []
        for r in range(3):
            alone = engine.infer([current[r]], [TASKS[r]], [seeds[r]], [histories[r]] if hist else None)[0]
            diffs.append(float(np.abs(together[r] - alone).max()))
        order = [2, 0]
        mixed = engine.infer([current[k] for k in order], [TASKS[k] for k in order], [seeds[k] for k in order], [histories[k] for k in order] if hist else None)
        diffs += [float(np.abs(mixed[i] - together[k]).max()) for i, k in enumerate(order)]
        check.max_diff = max(diffs)
        check.prompts = _prompts(engine, current[0], seeds[0], hist and histories[0])
    rtc_why = rtc_mod.unsupported_reason(engine.policy) if engine.kind.inputs == "current" else "needs a flow-matching sampler"
    check.rtc = "yes" if rtc_why is None else f"no: {rtc_why}"
    graph_why = static_sampler.unsupported_reason(engine.policy)
    check.static_sampler = "yes" if graph_why is None else "no"
    if timing:
        check.cpu_ms = {b: _median_ms(engine, b) for b in (1, 4)}
    return check


def _prompts(engine: Any, obs: dict[str, np.ndarray], seed: int, history: Any) -> str:
    """``yes`` if two prompts give two chunks for the same observation and noise."""
    tokenizes = any("tokenizer" in (getattr(type(s), "_registry_name", "") or "") for s in getattr(engine.preprocessor, "steps", []))
    if not tokenizes:
        return "no language input"
    rows = engine.infer([obs, obs], list(TASKS[:2]), [seed, seed], [history, history] if history else None)
    return "yes" if float(np.abs(rows[0] - rows[1]).max()) > 1e-6 else "tokenized, no effect on the chunk"


def _median_ms(engine: Any, b: int, reps: int = 5) -> float:
    obs = [engine.example_observation(seed=k) for k in range(b)]
    engine.infer(obs, ["warm-up"] * b)
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        engine.infer(obs, ["timed"] * b)
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def _saved_type(path: str) -> str:
    import json
    from pathlib import Path

    try:
        return str(json.loads((Path(path) / "config.json").read_text()).get("type", "?"))
    except (OSError, ValueError):
        return "?"


# LeRobot 0.6.1's chunking types that cannot be built here without their pretrained backbone
# (read from their constructors and tried with no hub access; research/policy_survey has the runs).
NOT_BUILT_OFFLINE: dict[str, str] = {
    "groot": "builds GR00T N1.7 from its pretrained checkpoint and Cosmos-Reason2-2B in the constructor; no config-only path",
    "wall_x": "loads x-square-robot/wall-oss-flow (Qwen2.5-VL MoE), its processor and a FAST tokenizer in the constructor",
    "eo1": "its config reads Qwen/Qwen2.5-VL-3B-Instruct's config from the hub",
    "evo1": "loads OpenGVLab/InternVL3-1B-hf in the constructor",
    "fastwam": "loads the Wan2.2-TI2V-5B VAE and UMT5 from the hub",
    "molmoact2": "loads its MolmoAct2 backbone and config from the hub in the constructor",
    "vla_jepa": "loads Qwen/Qwen3-VL-2B-Instruct and facebook/vjepa2-vitl-fpc64-256 in the constructor",
    "lingbot_va": "its first predict loads the VAE, UMT5-XXL and tokenizer of robbyant/lingbot-va-base",
}

COLUMNS = (
    "LeRobot type", "built offline", "served", "batched = alone (1e-5)", "chance", "observation history", "per-robot prompt", "RTC",
    "static sampler", "CPU ms b=1 / b=4",
)  # fmt: skip
TIMING = COLUMNS.index("CPU ms b=1 / b=4")
ALONE_TOLERANCE = 1e-5  # float32 on the CPU: a batch may sum in another order than a single row


def table_row(check: PolicyCheck, built: str) -> list[str]:
    """One row of the coverage table for a policy that was built (``built``: how)."""
    if check.refusal is not None:
        return [check.type, built, f"refused: {check.refusal.split('per robot: ', 1)[-1]}", *["—"] * 7]
    if check.max_diff is None:
        raise ValueError(f"{check.type}: nothing measured")
    alone = ("yes" if check.max_diff <= ALONE_TOLERANCE else f"NO (max diff {check.max_diff:.1e})") + (
        " (chance frozen)" if check.frozen else ""
    )
    history = "current observation" if check.history == 1 else f"last {check.history}, kept per robot"
    ms = " / ".join(f"{check.cpu_ms[b]:.1f}" if check.cpu_ms[b] < 10 else f"{check.cpu_ms[b]:.0f}" for b in (1, 4)) if check.cpu_ms else "—"
    rtc = "yes" if check.rtc == "yes" else "no"
    return [check.type, built, "yes", alone, check.randomness, history, check.prompts, rtc, check.static_sampler, ms]


def unbuilt_row(kind: str) -> list[str]:
    """The row of a type that needs its hub checkpoint to be built."""
    from lerobot_armory.engine.policy_kinds import KINDS

    info = KINDS[kind]
    why = info.refuse(None)  # the built-in refusals do not read the config
    served = f"refused: {why}" if why else "not run here; with its checkpoint: served as stateless, current observation"
    return [kind, f"no: {NOT_BUILT_OFFLINE[kind]}", served, "—", info.randomness(None) if not why else "—", *["—"] * 5]


def installed_plugins() -> list[str]:
    """``lerobot_policy_*`` distributions installed here (LeRobot's third-party policy plugins)."""
    from importlib import metadata

    names = {(d.metadata["Name"] or "").replace("-", "_").lower() for d in metadata.distributions()}
    return sorted(n for n in names if n.startswith("lerobot_policy_"))


def plugin_row(name: str) -> list[str]:
    """A plugin's row: its types are registered when the server loads, and served as unknown types."""
    return [name, "plugin (not built here)", "as an unknown type: stateless, refused with n_obs_steps > 1", "not checked", *["—"] * 6]


def markdown(rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def verdicts(text: str) -> list[list[str]]:
    """The rows of a markdown coverage table without the timing column (what a test compares)."""
    rows = []
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("| LeRobot type"):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            rows.append(cells[:TIMING] + cells[TIMING + 1 :])
    return rows

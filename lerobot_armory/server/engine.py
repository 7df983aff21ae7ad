"""The inference engine: any LeRobot chunking policy, run batched.

One call of :meth:`PolicyEngine.infer` is one forward pass for the whole batch:
wire arrays → stacked tensors → LeRobot pre-processor → ``predict_action_chunk`` →
post-processor → one ``(H, action_dim)`` chunk per robot. No Python loop over robots or actions
touches the model.

The policy is loaded exactly the way ``--policy.path`` is loaded by LeRobot itself
(``PreTrainedConfig.from_pretrained``, the policy class's ``from_pretrained``,
``make_pre_post_processors(pretrained_path=...)``), so a local directory and a hub id behave alike.
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.errors import ConfigError
from lerobot_armory.latency import LatencyProfile
from lerobot_armory.wire import FeatureSpec

log = logging.getLogger(__name__)

# Optional sidecar a policy directory may carry (the demo policy writes it): action names.
SIDECAR = "armory.json"


@dataclass
class PolicyOptions:
    """``--policy.*`` options.

    Attributes:
        path: local policy directory or hub id (``lerobot/pi05_libero``).
        device: torch device (``cuda``, ``cuda:1``, ``cpu``, ``mps``); default: cuda if available.
        cpu_threads: torch intra-op threads when the policy runs on the CPU; default: all cores
            but one, so the network threads keep a core (oversubscribing makes every batch slower).
    """

    path: str = ""
    device: str | None = None
    cpu_threads: int | None = None


class PolicyEngine:
    """A loaded LeRobot policy with its processors, served in batches.

    Raises:
        ConfigError: the path is missing/unloadable, or the policy does not predict chunks.
    """

    def __init__(self, options: PolicyOptions) -> None:
        import torch

        if not options.path:
            raise ConfigError("policy.path", "no policy given; pass --policy.path=DIR or a hub id")
        self.device = options.device or ("cuda" if torch.cuda.is_available() else "cpu")
        self.cpu_threads: int | None = None
        if self.device == "cpu":
            threads = options.cpu_threads or max(1, (os.cpu_count() or 2) - 1)
            if threads < 1:
                raise ConfigError("policy.cpu_threads", f"must be >= 1, got {threads}")
            self.cpu_threads = threads
        self._threads_set: set[int] = set()
        self._set_thread_count()
        self.path = options.path
        self.config, self.policy, self.preprocessor, self.postprocessor = _load(options.path, self.device)
        self.input_features: dict[str, Any] = dict(self.config.input_features)
        action = self.config.output_features.get("action")
        if action is None:
            raise ConfigError("policy.path", f"{options.path}: the policy has no 'action' output feature")
        self.action_dim = int(action.shape[0])
        self.action_names = _action_names(options.path, self.action_dim)
        self.wire_features = expected_wire_features(self.input_features)
        # The chunk size is whatever predict_action_chunk really returns (checked by a dry run).
        self.chunk_size = self._dry_run()

    @property
    def description(self) -> str:
        return f"{self.config.type} from {self.path} on {self.device}"

    def _dry_run(self) -> int:
        try:
            out = self.infer([self.example_observation(seed=0)], ["dry run"])
        except NotImplementedError:
            raise ConfigError("policy.path", f"{self.path}: {self.config.type} does not predict action chunks") from None
        if out.ndim != 3 or out.shape[0] != 1 or out.shape[2] != self.action_dim:
            raise ConfigError(
                "policy.path",
                f"{self.path}: predict_action_chunk returned shape {list(out.shape)}, expected (1, H, {self.action_dim})",
            )
        return int(out.shape[1])

    def example_observation(self, seed: int) -> dict[str, np.ndarray]:
        """A random observation with the wire features' dtypes and shapes (profiling, tests)."""
        rng = np.random.default_rng(seed)
        obs = {}
        for spec in self.wire_features:
            if spec.dtype == "uint8":
                obs[spec.name] = rng.integers(0, 256, spec.shape, dtype=np.uint8)
            else:
                obs[spec.name] = rng.standard_normal(spec.shape).astype(spec.dtype)
        return obs

    def _set_thread_count(self) -> None:
        """Apply ``cpu_threads`` in the calling thread: OpenMP's thread count is per thread, so a
        serving thread that skipped this would run the model on every core (measured here: 20-40 %
        slower batches on 2 cores while network threads compete)."""
        import torch

        ident = threading.get_ident()
        if self.cpu_threads is not None and ident not in self._threads_set:
            torch.set_num_threads(self.cpu_threads)
            self._threads_set.add(ident)

    def infer(self, observations: Sequence[dict[str, np.ndarray]], tasks: Sequence[str]) -> np.ndarray:
        """One batched forward pass. Returns float32 ``(B, H, action_dim)`` on the CPU."""
        import torch

        self._set_thread_count()

        batch = self.to_batch(observations)
        batch["task"] = list(tasks)
        with torch.inference_mode():
            processed = self.preprocessor(batch)
            actions = self.policy.predict_action_chunk(processed)
            actions = self.postprocessor(actions)
        return actions.detach().to("cpu", torch.float32).numpy()

    def to_batch(self, observations: Sequence[dict[str, np.ndarray]]) -> dict[str, Any]:
        """Stack the robots' wire arrays into policy tensors (images: uint8 HWC → float CHW in [0, 1])."""
        import torch

        batch: dict[str, Any] = {}
        for name, feature in self.input_features.items():
            arrays = [obs[name] for obs in observations]
            if _is_visual(feature) and any(a.dtype == np.uint8 for a in arrays):
                if all(a.dtype == np.uint8 for a in arrays):  # the common case: one stack, one permute
                    batch[name] = torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).float().div_(255.0)
                else:  # robots may send float CHW instead: convert each, then stack
                    batch[name] = torch.stack([_image_chw(a) for a in arrays])
            else:
                batch[name] = torch.from_numpy(np.stack(arrays)).float()
        return batch

    def profile(self, max_batch_size: int, warmup: int = 2, reps: int = 5, log_progress: bool = True) -> LatencyProfile:
        """Measure ``d_infer(b)`` for b = 1..max_batch_size (median of ``reps`` after ``warmup``).

        Measured medians are made non-decreasing (a larger batch is never cheaper to schedule
        for), as the schedulers require.
        """
        values: list[float] = []
        for b in range(1, max_batch_size + 1):
            obs = [self.example_observation(seed=k) for k in range(b)]
            tasks = ["profiling"] * b
            for _ in range(warmup):
                self.infer(obs, tasks)
            times = []
            for _ in range(reps):
                start = time.perf_counter()
                self.infer(obs, tasks)
                times.append((time.perf_counter() - start) * 1000.0)
            ms = statistics.median(times)
            values.append(max(ms, values[-1]) if values else ms)
            if log_progress:
                log.info("profiled b=%d: %.1f ms (median of %d)", b, ms, reps)
        return LatencyProfile(f"profiled:{self.config.type}", tuple(values), self.device, "profiled")


def _load(path: str, device: str):
    """Load config, policy and processors the way LeRobot loads ``--policy.path``."""
    try:
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.utils.import_utils import register_third_party_plugins
    except ImportError as exc:  # pragma: no cover - lerobot is a hard dependency
        raise ConfigError("policy.path", f"cannot import lerobot: {exc}") from None
    import lerobot_armory.policies  # noqa: F401  (registers armory_planner)

    try:
        register_third_party_plugins()  # lerobot_policy_* packages the user installed
    except Exception as exc:  # a broken plugin must not stop the policies that do work
        log.warning("third-party plugin registration failed: %s", exc)
    local = Path(path)
    if (local.exists() or path.startswith((".", "/"))) and not (local / "config.json").is_file():
        raise ConfigError("policy.path", f"{path}: not a LeRobot policy directory (no config.json)")
    try:
        config = PreTrainedConfig.from_pretrained(path)
        config.device = device
        policy = get_policy_class(config.type).from_pretrained(path, config=config)
        policy.to(device)
        policy.eval()
        pre, post = make_pre_post_processors(
            config,
            pretrained_path=path,
            preprocessor_overrides={"device_processor": {"device": device}},
            postprocessor_overrides={"device_processor": {"device": "cpu"}},
        )
    except ConfigError:
        raise
    except Exception as exc:  # hub errors, missing files, incompatible configs...
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError("policy.path", f"cannot load policy from {path}: {type(exc).__name__}: {first}") from None
    if not hasattr(policy, "predict_action_chunk"):
        raise ConfigError("policy.path", f"{path}: {config.type} does not predict action chunks")
    return config, policy, pre, post


def _image_chw(array: np.ndarray):
    import torch

    t = torch.from_numpy(np.ascontiguousarray(array))
    return t.permute(2, 0, 1).float().div_(255.0) if t.dtype == torch.uint8 else t.float()


def _is_visual(feature: Any) -> bool:
    return getattr(feature.type, "name", str(feature.type)) == "VISUAL"


def expected_wire_features(input_features: dict[str, Any]) -> list[FeatureSpec]:
    """What a robot must send for these policy inputs: images as uint8 (H, W, 3), the rest float32."""
    out = []
    for name, feature in input_features.items():
        shape = tuple(int(d) for d in feature.shape)
        if _is_visual(feature):
            c, h, w = shape
            out.append(FeatureSpec(name, "uint8", (h, w, c)))
        else:
            out.append(FeatureSpec(name, "float32", shape))
    return out


def check_features(declared: Sequence[FeatureSpec], expected: Sequence[FeatureSpec]) -> list[str]:
    """Every mismatch between a robot's declared features and the policy's inputs (empty: OK).

    Images may be declared as uint8 (H, W, 3) or as float32 (3, H, W) in [0, 1].
    """
    problems = []
    exp = {s.name: s for s in expected}
    seen = set()
    for spec in declared:
        if spec.name in seen:
            problems.append(f"feature {spec.name!r} declared twice")
            continue
        seen.add(spec.name)
        want = exp.get(spec.name)
        if want is None:
            problems.append(f"unexpected feature {spec.name!r} {spec.describe()}: the policy does not use it")
            continue
        ok = spec == want
        if not ok and want.dtype == "uint8" and len(want.shape) == 3:  # image: CHW float also fine
            h, w, c = want.shape
            ok = spec.dtype == "float32" and spec.shape == (c, h, w)
        if not ok:
            problems.append(f"feature {spec.name!r}: declared {spec.describe()}, the policy needs {want.describe()}")
    for name in exp:
        if name not in seen:
            problems.append(f"missing feature {name!r}: the policy needs {exp[name].describe()}")
    return problems


def _action_names(path: str, action_dim: int) -> list[str]:
    sidecar = Path(path) / SIDECAR
    if sidecar.is_file():
        try:
            names = json.loads(sidecar.read_text()).get("action_names")
            if isinstance(names, list) and len(names) == action_dim and all(isinstance(n, str) for n in names):
                return names
        except (OSError, json.JSONDecodeError):
            log.warning("ignoring unreadable %s", sidecar)
    return [f"action_{k}" for k in range(action_dim)]

"""The inference engine: any LeRobot chunking policy, run batched.

Over 500 lines: one class whose parts share the device thread, the upload buffers and the
recorded graphs. Loading lives in ``loading.py``, start-up for serving in ``startup.py``, the
samplers themselves in ``lerobot_armory.acceleration``; the sampler choice (``_choose_sampler``)
is the next piece to leave.

One call of :meth:`PolicyEngine.infer` is one forward pass for the whole batch:
wire arrays → stacked tensors on the device → LeRobot pre-processor → ``predict_action_chunk`` →
post-processor → one ``(H, action_dim)`` chunk per robot. No Python loop over robots or actions
touches the model.

The policy is loaded exactly the way ``--policy.path`` is loaded by LeRobot itself
(``PreTrainedConfig.from_pretrained`` with the ``--policy.<field>`` overrides, the policy class's
``from_pretrained``, ``make_pre_post_processors(pretrained_path=...)``), so a local directory and a
hub id behave alike.

On a GPU the host side does as little as it can: images are stacked as uint8 into a reusable
pinned buffer, copied asynchronously (a quarter of the bytes of float32) and converted to float
on the device; the only synchronisation of a batch is the copy of its actions back to the host.
Every batch size is warmed up (and compiled, with ``--policy.compile_model=true``) before the
first robot is served; a compiled model is kept only where it measured faster than eager. Every
forward pass — dry run, warm-up, profiling, serving — runs on the engine's one device thread,
because torch.compile's CUDA graphs keep per-thread state (a graph recorded on one thread cannot
be replayed from another).

Flow-matching policies (π0, π0.5, SmolVLA) start from Gaussian noise. The engine draws it per
request from a seed (:func:`~lerobot_armory.engine.protocol.noise_seed`: robot id and chunk id), so a robot's chunk does not depend
on who shared its batch, and a chunk can be recomputed alone.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import inspect
import json
import logging
import os
import statistics
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.engine import history as history_mod
from lerobot_armory.engine import policy_kinds
from lerobot_armory.engine import rtc as rtc_mod
from lerobot_armory.engine.loading import first_line, load_policy
from lerobot_armory.engine.options import EngineOptions, PolicyOptions

from lerobot_armory.policies.layout import SIDECAR
from lerobot_armory.feature_spec import FeatureSpec

log = logging.getLogger(__name__)

# What ``_choose_sampler`` sets: kept by ``use_sampler`` so that refused options change nothing.
_SAMPLER_STATE = (
    "engine_options", "matmul_precision", "sampler", "graphs_wanted", "sampler_note", "fused_kernels", "prompt_buckets", "_prompt_forced", "_prompt_full",
    "_sampler_takes_state", "_sampler_cameras",
)

# Pre-processor steps known to leave images alone or to work on any device. Images go to the device
# before the pre-processor only when every step before its device step is one of these (GR00T's
# steps, for one, pull images back to the host with .cpu().numpy(): for such a policy the images
# stay on the host and LeRobot's device step moves them, as before).
DEVICE_AGNOSTIC_STEPS = frozenset(
    {
        "rename_observations_processor", "to_batch_processor", "relative_actions_processor",
        "normalizer_processor", "tokenizer_processor", "pi05_prepare_state_tokenizer_processor_step",
        "pi0_new_line_processor", "smolvla_new_line_processor",
    }
)  # fmt: skip


class PolicyEngine:
    """A loaded LeRobot policy with its processors, served in batches.

    Raises:
        ConfigError: the path is missing/unloadable, an override names no field of the policy,
            or the policy does not predict chunks.
    """

    def __init__(
        self, options: PolicyOptions, rtc: rtc_mod.RTCOptions | None = None, engine: EngineOptions | None = None
    ) -> None:
        import torch

        self.engine_options = engine or EngineOptions()
        self.engine_options.validate()

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
        _register_cuda_guard_here()  # before the device thread traces anything
        # The one thread every forward pass runs on (see the module docstring).
        self._device_thread = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="armory-device")
        self.path = options.path
        self.overrides = list(options.overrides)
        self.config, self.policy, self.preprocessor, self.postprocessor = load_policy(options.path, self.device, options.overrides)
        self.matmul_precision = self._apply_matmul_precision()
        # A server never trains: without gradients on the weights, RTC's guidance step records no
        # autograd graph through the model.
        for param in self.policy.parameters():
            param.requires_grad_(False)
        self.kind = policy_kinds.kind_of(self.config)
        # Observations per row: the serving core keeps each robot's last ones (1: the current).
        self.history_steps = max(1, self.kind.history(self.config))
        self.rtc_options = rtc if rtc is not None and rtc.enabled else None
        if self.rtc_options is not None and self.kind.inputs != "current":
            raise ConfigError("rtc.enabled", f"{self.config.type}: real-time chunking needs a flow-matching policy (π0, π0.5, SmolVLA)")
        if not self.kind.known:
            log.warning(
                "%s is not a policy type lerobot-armory has checked: served as stateless (its chunks as if alone is not verified)",
                self.config.type,
            )
        self.rtc = rtc_mod.enable(self.policy, self.rtc_options) if self.rtc_options is not None else None
        # Images go to the device before the pre-processor where its steps allow (to_batch).
        self.early_upload = _early_upload_ok(self.preprocessor)
        # The prompt columns a batch uses, read on the host (no read-back to choose its bucket).
        from lerobot_armory.engine.prompt_columns import HostPromptColumns

        self._known_steps = _known_steps_only(self.preprocessor)
        self._prompt_columns = HostPromptColumns(self.preprocessor) if self._known_steps else None
        # The static sampler (and its CUDA graphs) in place of the policy's own, where it applies.
        self.sampler: Any = None  # cuda_graphs.BucketedSampler
        self.graphs_wanted, self.sampler_note = self._choose_sampler()
        from lerobot_armory.policies.cameras import placeholder_cameras

        # Placeholder cameras (``--policy.empty_cameras``) are not on the wire: the policy's own
        # image step fills them (−1 pixels, masked), as LeRobot does when a dataset lacks them.
        placeholders = placeholder_cameras(self.config)
        self.input_features: dict[str, Any] = {k: v for k, v in self.config.input_features.items() if k not in placeholders}
        action = self.config.output_features.get("action")
        if action is None:
            raise ConfigError("policy.path", f"{options.path}: the policy has no 'action' output feature")
        self.action_dim = int(action.shape[0])
        self.action_names = _action_names(options.path, self.action_dim)
        self.wire_features = expected_wire_features(self.input_features)
        if self.kind.noise is not None:
            self.noise_shape = self.kind.noise(self.config)
        else:
            self.noise_shape = None if self.kind.known else _noise_shape(self.policy)
        # Pinned host buffers for asynchronous copies, one per (feature, batch size); reused
        # because every batch ends with a synchronisation (its actions come back to the host).
        self._pinned = torch.device(self.device).type == "cuda"
        self._staging: dict[tuple[str, int], Any] = {}
        self.compiled_kept: bool | None = None  # after warmup(): compiled model kept (None: not compiled)
        # The chunk size is whatever predict_action_chunk really returns (checked by a dry run).
        self.chunk_size = self._dry_run()
        if self.rtc is not None and self.sampler is None:
            self._check_rtc_reached()

    def use_sampler(self, options: EngineOptions) -> None:
        """Serve through what ``options`` asks (LeRobot's sampler, the static one, CUDA graphs) from
        now on; graphs are recorded by the next :meth:`warmup`. Lets a benchmark compare samplers on
        one loaded policy (loading the full π0.5 takes minutes).

        Raises:
            ConfigError: as the constructor does for these options; the engine then serves as it
                did (its sampler, graphs and options kept).
        """
        options.validate()
        kept = {name: getattr(self, name) for name in _SAMPLER_STATE}
        try:
            self.engine_options = options
            self.matmul_precision = self._apply_matmul_precision()
            self.sampler = None  # the recorded graphs (and their memory pool) go once this call returns
            self.graphs_wanted, self.sampler_note = self._choose_sampler()
        except BaseException:
            for name, value in kept.items():
                setattr(self, name, value)
            self._apply_matmul_precision()
            raise

    @property
    def vision_cast(self) -> str | None:
        """The dtype π0.5's vision tower was cast to (``--engine.vision_dtype``), read off its
        weights (LeRobot keeps them float32 in every dtype); None: not cast, or not a π0.5."""
        import torch

        from lerobot_armory.acceleration.pi05_static import vision_dtype_of

        dtype = vision_dtype_of(self.policy)
        return None if dtype is None or dtype == torch.float32 else str(dtype).removeprefix("torch.")

    def _apply_matmul_precision(self) -> str:
        """Set torch's float32 matmul precision (process-wide) as the options ask; returns it."""
        import torch

        dtype = getattr(self.config, "dtype", None)
        precision = self.engine_options.resolved_matmul_precision(str(self.device), dtype if isinstance(dtype, str) else None)
        torch.set_float32_matmul_precision(precision)
        return precision

    def _choose_sampler(self) -> tuple[bool, str | None]:
        """Install the static sampler if the options and the policy allow it; returns (record CUDA
        graphs at warm-up, why the policy's own sampler is used instead or None)."""
        import torch

        from lerobot_armory.acceleration import static_sampler
        from lerobot_armory.engine.cuda_graphs import BucketedSampler

        o = self.engine_options
        self.fused_kernels = False
        self.float32_products = False
        self.hand_kernels = self.attention_kernels = False
        self._sampler_takes_state = False  # the static sampler embeds the state (π0, SmolVLA)
        self._sampler_cameras: tuple[str, ...] = ()  # the cameras its inputs carry, in order
        self.prompt_buckets: tuple[int, ...] = ()  # fitted prompt lengths, ascending (none: the full length)
        self._prompt_full: int | None = None  # the tokenizer's max length: every batch's when no bucket is smaller
        self._prompt_forced: int | None = None  # while profiling: every batch at this prompt length
        cuda = torch.device(self.device).type == "cuda"
        why = static_sampler.unsupported_reason(self.policy)
        if o.cuda_graphs == "on" and not cuda:
            raise ConfigError("engine.cuda_graphs", f"on needs a CUDA device; this engine runs on {self.device}")
        graphs = o.cuda_graphs == "on" or (o.cuda_graphs == "auto" and cuda and why is None)
        static = graphs if o.static_sampler is None else o.static_sampler
        if static and why is not None:
            option = "cuda_graphs" if o.static_sampler is None else "static_sampler"
            raise ConfigError(f"engine.{option}", why)
        dtype = getattr(self.config, "dtype", None)
        vision = o.resolved_vision_dtype(str(self.device), dtype if isinstance(dtype, str) else None, static)
        if self.vision_cast is not None and (not static or vision != self.vision_cast):
            raise ConfigError(
                "engine.vision_dtype", f"the vision tower was cast to {self.vision_cast} for the static sampler; "
                "serving it otherwise needs the policy loaded again"
            )
        if not static and vision != "float32":
            raise ConfigError("engine.vision_dtype", "runs the static sampler's vision tower, which is off here; --engine.static_sampler=true turns it on")
        if not static and o.compile_sampler:
            raise ConfigError(
                "engine.compile_sampler", f"compiles the static sampler, which is off here ({why or 'no CUDA device'}); "
                "--engine.static_sampler=true turns it on"
            )
        if not static:
            note = why if o.cuda_graphs == "auto" and cuda else None
            if note is not None:
                log.info("CUDA graphs off, the policy's own sampler serves: %s", note)
            return False, note
        full = self._tokenizer_max_length()
        if isinstance(full, int) and full > 0:  # checked before the sampler may cast the vision tower
            from lerobot_armory.engine.cuda_graphs import parse_prompt_buckets

            self.prompt_buckets = parse_prompt_buckets(o.prompt_buckets, full)
            self._prompt_full = full
        rtc = self.rtc_options
        try:
            sampler = static_sampler.make_static_sampler(
                self.policy,
                guided=rtc is not None,
                max_guidance_weight=rtc.max_guidance_weight if rtc else 10.0,
                attention=o.attention,
                fused=o.fused_kernels,
                vision_dtype=None if vision == "float32" else getattr(torch, vision),
            )
        except ValueError as exc:  # e.g. --policy.num_inference_steps=0
            raise ConfigError("policy", f"{self.path}: the static sampler cannot run it: {exc}") from None
        if sampler.unfused_reason is not None:
            log.info("the static sampler runs LeRobot's own sequence of operations (fused kernels off): %s", sampler.unfused_reason)
        self.fused_kernels = sampler.fused
        self.float32_products = bool(getattr(sampler.ops, "float32_products", False))  # π0 family, bf16, CUDA
        if not self.float32_products and str(self.device).startswith("cuda") and getattr(sampler.ops, "compute_dtype", None) == torch.bfloat16:
            # Expected off on a CPU or for float32 weights; on a GPU in bf16, say why.
            log.info("the output projections stay bf16 (residual sums read two dtypes): %s", sampler.ops.float32_products_reason)
        self._sampler_takes_state, self._sampler_cameras = sampler.takes_state, sampler.cameras
        if getattr(self.config, "compile_model", False):
            log.info("--policy.compile_model is unused: the static sampler serves (--engine.compile_sampler=true compiles it)")
        if o.compile_sampler and not sampler.compilable:
            raise ConfigError("engine.compile_sampler", f"{self.config.type}'s static sampler is not compiled yet; leave it false")
        if o.compile_sampler:
            sampler.compile_layers()  # compiled at warm-up, on the first batch through them
        self.hand_kernels = bool(getattr(sampler.ops, "hand_kernels", False))  # π0 family, Triton
        if not self.hand_kernels and str(self.device).startswith("cuda") and sampler.fused and hasattr(sampler.ops, "hand_kernels"):
            log.info("PyTorch's operations serve where the Triton kernels would: %s", sampler.ops.hand_kernels_reason)
        # attention's kernels are refused wherever the other Triton kernels are (their reason comes first)
        self.attention_kernels = bool(getattr(sampler.ops, "attention_kernels", False))
        if self.hand_kernels and not self.attention_kernels:
            log.info("PyTorch's operations serve the rotary embedding and attention's softmax: %s", sampler.ops.attention_kernels_reason)
        sample = sampler.sample_compiled if o.compile_sampler else sampler.sample
        rest = sampler.sample_embedded_compiled if o.compile_sampler else sampler.sample_embedded
        # The vision tower is recorded apart from the rest (BucketedSampler.start) where the images
        # reach the device before the pre-processor and no step of it can touch them.
        split = o.early_vision and self.early_upload and self._known_steps
        self.sampler = BucketedSampler(sample, sampler.prepare, uncompiled=sampler.sample, vision=sampler.vision if split else None, rest=rest if split else None)
        return graphs, None

    def _tokenizer_max_length(self) -> int | None:
        """The prompt length the pre-processor's tokenizer pads or truncates to: its step's own
        ``max_length`` (saved with the processor, so ``--policy.tokenizer_max_length`` does not
        reach it), else the config's."""
        for step in getattr(self.preprocessor, "steps", []):
            if type(step).__name__ == "TokenizerProcessorStep" and isinstance(getattr(step, "max_length", None), int):
                return int(step.max_length)
        return getattr(self.config, "tokenizer_max_length", None)

    @property
    def unrecorded_batches(self) -> int:
        """Batches served eagerly although CUDA graphs were recorded (no graph fitted them)."""
        return self.sampler.unrecorded if self.sampler is not None else 0

    @property
    def description(self) -> str:
        notes = [f"dtype={self.config.dtype}"] if isinstance(getattr(self.config, "dtype", None), str) else []
        if self.matmul_precision != "highest":
            notes.append(f"float32 matmul precision {self.matmul_precision}")
        if self.compiled_kept is not None:
            notes.append("compiled" if self.compiled_kept else "eager (compiled was slower)")
        if self.sampler is not None:
            buckets = ",".join(map(str, self.sampler.buckets)) or "-"
            if self.engine_options.compile_sampler:
                notes.append("static sampler compiled")
            if self.fused_kernels:
                notes.append("fused kernels")
                if self.float32_products:
                    notes.append("output projections in float32")
                if self.hand_kernels:
                    notes.append("Triton kernels" + ("" if self.attention_kernels else " (not attention's)"))
            if self.vision_cast is not None:
                notes.append(f"vision tower in {self.vision_cast}")
            if self.prompt_buckets:
                notes.append(f"prompts cut to {','.join(map(str, self.prompt_buckets))} tokens")
            if self.sampler.captured:
                total = sum(self.sampler.capture_s.values())
                notes.append(f"static sampler, CUDA graphs for buckets {buckets} ({total:.1f} s to record)")
                if self.sampler.vision_graphs:
                    notes.append("the vision tower's graph started before the pre-processor")
            else:
                why = self.sampler_note or self.device
                notes.append(f"static sampler, buckets {buckets}, not recorded" + ("" if self.graphs_wanted else f" ({why})"))
        elif self.sampler_note is not None:
            notes.append("LeRobot's sampler (no CUDA graphs)")
        if self.rtc_options is not None:
            o = self.rtc_options
            notes.append(
                f"RTC from the mirror: horizon {o.execution_horizon}, {o.prefix_attention_schedule.upper()}, "
                f"max guidance {o.max_guidance_weight:g}, delay margin {o.delay_margin}"
            )
        return f"{self.config.type} from {self.path} on {self.device}" + (f" ({', '.join(notes)})" if notes else "")

    def _dry_run(self) -> int:
        try:
            out = self.infer([self.example_observation(seed=0)], ["dry run"])
        except NotImplementedError:
            raise ConfigError("policy.path", f"{self.path}: {self.config.type} does not predict action chunks") from None
        except Exception as exc:  # e.g. --policy.num_inference_steps=0: ZeroDivisionError inside the sampler
            where = f" with {' '.join('--policy.' + o for o in self.overrides)}" if self.overrides else ""
            raise ConfigError("policy", f"{self.path}{where}: a first forward pass failed: {first_line(exc)}") from None
        if out.ndim != 3 or out.shape[0] != 1 or out.shape[2] != self.action_dim:
            raise ConfigError(
                "policy.path",
                f"{self.path}: predict_action_chunk returned shape {list(out.shape)}, expected (1, H, {self.action_dim})",
            )
        return int(out.shape[1])

    def _check_rtc_reached(self) -> None:
        """A guided batch of two must reach the per-row processor (a policy whose sampler does not
        forward LeRobot's RTC arguments is refused here, not served unguided)."""
        assert self.rtc is not None
        before = self.rtc.calls
        self.infer_guided([self.example_observation(seed=k) for k in range(2)], ["dry run"] * 2, None, self.example_prefixes(2))
        if self.rtc.calls == before:
            raise ConfigError("rtc.enabled", f"{self.config.type}: the policy's sampler never applied the RTC guidance")

    def example_prefixes(self, batch_size: int) -> list[rtc_mod.Prefix]:
        """Synthetic RTC prefixes for profiling: a full leftover, the delay a quarter of a chunk."""
        rng = np.random.default_rng(batch_size)
        h = self.chunk_size
        return [rtc_mod.Prefix(rng.standard_normal((h, self.action_dim)).astype(np.float32), h // 4) for _ in range(batch_size)]

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

    def infer(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None = None,
        history: Sequence[Sequence[dict[str, np.ndarray]]] | None = None,
    ) -> np.ndarray:
        """One batched forward pass. Returns float32 ``(B, H, action_dim)`` on the CPU.

        ``tasks[k]`` is row k's prompt. ``noise_seeds[k]`` fixes row k's initial noise for a
        policy that takes one (default: 0..B-1); other policies ignore it. With
        ``history_steps > 1``, ``history[k]`` is row k's last ``history_steps`` observations,
        oldest first, the last one ``observations[k]`` (None: the current one repeated, as
        LeRobot fills a fresh episode's queue).
        """
        return self.on_device(self._infer, observations, tasks, noise_seeds, None, history)[0]

    def infer_guided(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None,
        prefixes: Sequence[rtc_mod.Prefix | None],
    ) -> tuple[np.ndarray, np.ndarray]:
        """One batched forward pass with real-time chunking: row k guided by ``prefixes[k]``
        (None: unguided). Returns ``(actions, model_actions)``: the chunks as robots get them,
        and the same chunks in the policy's own action space (the next leftovers are cut from
        those, as LeRobot's ``ActionQueue`` keeps its "original" actions).

        Raises:
            RuntimeError: the engine was built without ``--rtc.enabled``.
        """
        if self.rtc is None:
            raise RuntimeError("infer_guided needs an engine built with --rtc.enabled=true")
        if len(prefixes) != len(observations):
            raise ValueError(f"{len(prefixes)} prefixes for {len(observations)} observations")
        return self.on_device(self._infer, observations, tasks, noise_seeds, prefixes)

    def on_device(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run ``fn`` on the engine's device thread and return its result (benchmarks time a bare
        forward pass through this, so that it runs where the served ones do)."""
        return self._device_thread.submit(fn, *args, **kwargs).result()

    def _infer(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None,
        prefixes: Sequence[rtc_mod.Prefix | None] | None = None,
        history: Sequence[Sequence[dict[str, np.ndarray]]] | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        import torch

        self._set_thread_count()
        try:
            steps = self.history_steps if self.kind.inputs != "current" else 1
            rows = self._history_rows(observations, history, steps)
            guided = prefixes is not None
            # RTC's guidance through LeRobot's sampler takes a gradient (of its own error, not of
            # the weights), which inference mode forbids: such batches run under no_grad instead.
            # The static sampler's guidance is closed-form.
            with torch.no_grad() if guided and self.sampler is None else torch.inference_mode():
                # Every input made in the batch's mode: a compiled sampler's guards tell inference
                # tensors from others, and one made outside would be a new shape to compile.
                batch = self.to_batch([obs for row in rows for obs in row])
                batch["task"] = [task for task in tasks for _ in range(steps)]
                self._start_vision(batch)
                kwargs = self._forward_kwargs(len(observations), noise_seeds, prefixes)
                processed = self.preprocessor(batch)
                if self.kind.inputs == "current":
                    model_actions = self.forward(processed, kwargs)
                else:
                    model_actions = history_mod.predict(self.policy, self.kind, processed, len(rows), steps, kwargs)
                actions = self.postprocessor(model_actions.clone() if guided else model_actions)
            # The one synchronisation of the batch (a no-op copy on the CPU).
            out = actions.detach().to("cpu", torch.float32).numpy()
            return out, (model_actions.detach().to("cpu", torch.float32).numpy() if guided else None)
        except BaseException:
            if self._pinned:  # a failed batch must not leave copies from the staging buffers in flight
                with contextlib.suppress(Exception):  # (a CUDA error would raise again here)
                    torch.cuda.synchronize(self.device)
            raise

    def _start_vision(self, batch: dict[str, Any]) -> None:
        """Start the batch's vision graph on its images, already on the device, so that the GPU
        runs the vision tower while the host runs the pre-processor (tokenizer, state, noise). It
        counts only if the pre-processor hands the sampler these very tensors (its steps, LeRobot's
        own known ones, leave images as they are: ``_known_steps_only``); the sampler checks that,
        and otherwise runs it again on what it is given."""
        if self.sampler is None or self.sampler.vision is None:
            return
        images = [batch.get(name) for name in self._sampler_cameras]
        if all(image is not None for image in images):
            self.sampler.start(images)

    def _forward_kwargs(
        self, rows: int, noise_seeds: Sequence[int] | None, prefixes: Sequence[rtc_mod.Prefix | None] | None
    ) -> dict[str, Any]:
        """What the forward pass takes beside the batch: each row's noise (seeds 0..rows-1 unless
        given), and with ``prefixes`` the RTC guidance."""
        kwargs: dict[str, Any] = {}
        if self.noise_shape is not None:
            kwargs["noise"] = self._noise(range(rows) if noise_seeds is None else noise_seeds)
        if prefixes is not None:
            assert self.rtc_options is not None
            o = self.rtc_options
            kwargs.update(rtc_mod.guidance_kwargs(prefixes, self.chunk_size, o.execution_horizon, self.device, o.delay_margin))
        return kwargs

    def _history_rows(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        history: Sequence[Sequence[dict[str, np.ndarray]]] | None,
        steps: int,
    ) -> list[list[dict[str, np.ndarray]]]:
        """Each row's observations, oldest first: its history when the policy takes one (the
        current observation repeated where none is given), else the current one alone."""
        if steps == 1:
            return [[obs] for obs in observations]
        if history is None:
            return [[obs] * steps for obs in observations]
        if len(history) != len(observations) or any(len(row) != steps for row in history):
            raise ValueError(f"history must hold {steps} observations for each of the {len(observations)} rows")
        return [list(row) for row in history]

    def forward(self, processed: dict[str, Any], kwargs: dict[str, Any]) -> Any:
        """The model alone on a pre-processed batch: ``(B, H, action_dim)`` in the policy's action
        space. ``kwargs`` are what LeRobot's ``predict_action_chunk`` takes (noise, RTC); the
        static sampler, where installed, runs instead of it (on the device thread, like every pass)."""
        if self.sampler is not None:
            return self.sampler(self._sampler_inputs(processed, kwargs))[:, :, : self.action_dim]
        return self.policy.predict_action_chunk(processed, **kwargs)

    def _sampler_inputs(self, processed: dict[str, Any], kwargs: dict[str, Any], prompt_length: int | None = None) -> Any:
        """The static sampler's inputs from a pre-processed batch and the keyword arguments the
        policy's own ``predict_action_chunk`` would have been given (noise, RTC prefixes), the
        prompt fitted to its prompt bucket (or to ``prompt_length``): cut, or padded where the
        tokenizer pads a batch to its longest prompt (SmolVLA), so that every batch has a length a
        graph was recorded for."""
        import torch
        from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS

        from lerobot_armory.acceleration.pi05_static import SamplerInputs

        noise = kwargs["noise"]
        inputs = SamplerInputs(
            tuple(processed[k] for k in self._sampler_cameras),
            processed[OBS_LANGUAGE_TOKENS], processed[OBS_LANGUAGE_ATTENTION_MASK], noise,
            state=self.policy.prepare_state(processed) if self._sampler_takes_state else None,
        )  # fmt: skip
        length = prompt_length or self._prompt_forced or self._prompt_bucket(inputs.masks)
        if length is None and self._prompt_full is not None and inputs.prompt_length < self._prompt_full:
            length = self._prompt_full  # padded, never cut: only a bucket's check knows what is padding
        if length is not None and length != inputs.prompt_length:
            inputs = inputs.prompt_fitted(length)
        if self.rtc is None:
            return inputs
        rows, length, dim = noise.shape
        if "prev_chunk_left_over" in kwargs:  # LeRobot's own weights per row, the leftover padded as LeRobot pads it
            inputs.rtc_weights = rtc_mod.row_weights(self.rtc, kwargs["inference_delay"], length).to(noise.device)
            inputs.rtc_leftover = rtc_mod.pad_leftover(kwargs["prev_chunk_left_over"], length, dim)
        else:  # no row has a prefix: zero weights leave every row unguided
            inputs.rtc_weights = noise.new_zeros(rows, length, 1)
            inputs.rtc_leftover = torch.zeros_like(noise)
        return inputs

    def _prompt_bucket(self, masks: Any) -> int | None:
        """The smallest prompt bucket that holds every row's prompt (None: keep them whole).
        LeRobot pads on the right; a mask that is not a run of ones then zeros keeps its length."""
        if not self.prompt_buckets:
            return None
        used = self._prompt_columns.used(masks) if self._prompt_columns is not None else None
        if used is None:  # a mask the pipeline did not just make on the host: read back (waits for the GPU)
            used = masks.any(dim=0).cpu()
        n = int(used.sum())
        if not bool(used[:n].all()):
            return None
        from lerobot_armory.engine.cuda_graphs import bucket_for

        return bucket_for(max(n, 1), self.prompt_buckets)

    def to_batch(self, observations: Sequence[dict[str, np.ndarray]]) -> dict[str, Any]:
        """Stack the robots' wire arrays into policy tensors: images on the device (uint8 HWC →
        float CHW in [0, 1], converted there; on the host for a pre-processor that needs them
        there, see :data:`DEVICE_AGNOSTIC_STEPS`), low-dimensional features on the host.

        Why the split: the images are nearly all the bytes, so they go early and as uint8; the
        state stays where LeRobot's pre-processor expects it (π0.5's prompt step discretises it
        with ``state.cpu()``, which on the device would be a synchronisation) and its own device
        step moves it with the tokens, asynchronously.
        """
        import torch

        batch: dict[str, Any] = {}
        for name, feature in self.input_features.items():
            arrays = [obs[name] for obs in observations]
            if _is_visual(feature) and all(a.dtype == np.uint8 for a in arrays):
                # The common case: one stack, one copy of uint8, the conversion on the device.
                staged = self._upload(name, arrays) if self.early_upload else torch.from_numpy(np.stack(arrays))
                batch[name] = staged.permute(0, 3, 1, 2).float().div_(255.0)
            elif _is_visual(feature):  # robots may send float CHW instead: convert each, then stack
                batch[name] = torch.stack([_image_chw(a) for a in arrays])
                if self.early_upload:
                    batch[name] = batch[name].to(self.device)
            else:
                batch[name] = torch.from_numpy(np.stack(arrays)).float()
        return batch

    def _upload(self, name: str, arrays: list[np.ndarray]):
        """``np.stack(arrays)`` as a tensor on the device (pinned staging + async copy on CUDA)."""
        import torch

        if not self._pinned:
            return torch.from_numpy(np.stack(arrays)).to(self.device)
        key = (name, len(arrays))
        buf = self._staging.get(key)
        if buf is None or tuple(buf.shape[1:]) != arrays[0].shape or buf.dtype != torch.from_numpy(arrays[0][:0]).dtype:
            buf = torch.from_numpy(np.stack(arrays)).pin_memory()
            self._staging[key] = buf
        else:
            np.stack(arrays, out=buf.numpy())
        return buf.to(self.device, non_blocking=True)

    def _noise(self, seeds: Sequence[int]):
        """Standard-normal float32 noise ``(B, H, D)``, row k drawn from ``seeds[k]`` alone."""
        import torch

        rows = [torch.randn(self.noise_shape, generator=torch.Generator().manual_seed(int(s)), dtype=torch.float32) for s in seeds]
        return self._upload("__noise__", [r.numpy() for r in rows])

    def warmup(self, max_batch_size: int, reps: int = 2, log_progress: bool = True) -> None:
        """Run every batch size 1..max_batch_size before serving (allocator, kernels, and the
        compilation of a compiled model happen now, not under the first robots). With a compiled
        model, time it against eager, both warm, and keep whichever is faster over all sizes.
        With the static sampler, the batch sizes are its buckets, and on a CUDA device each
        bucket's graph is recorded first (largest first: the smaller ones reuse its memory)."""
        if self.sampler is not None:
            from lerobot_armory.engine.cuda_graphs import parse_buckets

            self.sampler.set_buckets(parse_buckets(self.engine_options.graph_buckets, max_batch_size))
            if self.engine_options.compile_sampler:
                self._compile_shapes(log_progress)
            if self.graphs_wanted and not self.sampler.captured:
                self._record_graphs(log_progress)
        sizes = self._sizes(max_batch_size)
        compiled = _compiled_functions(self.policy) if self.sampler is None else []
        if compiled:
            _allow_recompiles(max_batch_size)
        self._time_sizes(sizes, 1, "warm-up" + (" (compiling)" if compiled else ""), log_progress)
        if not compiled:
            return
        fast_ms = self._time_sizes(sizes, reps, "compiled", log_progress)
        for owner, name, fn in compiled:
            setattr(owner, name, fn._torchdynamo_orig_callable)
        self._time_sizes(sizes, 1, "eager warm-up", False)  # eager's first passes are not its speed either
        eager_ms = self._time_sizes(sizes, reps, "eager", log_progress)
        self.compiled_kept = sum(fast_ms.values()) < sum(eager_ms.values())
        if self.compiled_kept:
            for owner, name, fn in compiled:
                setattr(owner, name, fn)
        log.info(
            "compiled %s ms vs eager %s ms (b=1..%d): keeping the %s model",
            [round(x, 1) for x in fast_ms.values()], [round(x, 1) for x in eager_ms.values()], max_batch_size,
            "compiled" if self.compiled_kept else "eager",
        )  # fmt: skip

    def _compile_shapes(self, log_progress: bool) -> None:
        """Compile the static sampler's layers now, not under robots, and run every (bucket,
        prompt length) through them once.

        Two functions are compiled, a VLM layer and an action-expert layer
        (``StaticPi05.compile_layers``), with the batch and prompt dimensions dynamic: each
        compiles once for bucket 1 and once for the buckets of two rows or more together, each
        compilation tracing one layer (seconds on a CPU for the narrow π0.5, where the whole
        sampler took minutes); the other shapes then only run. Said up front and each bucket
        logged as it is done; dynamo's recompile limit is raised to fit every shape anyway
        (past it dynamo refuses a whole-graph compilation: a batch's error), should a dimension
        be specialised after all. Graphs recorded afterwards replay the compiled kernels."""
        assert self.sampler is not None
        buckets, lengths = self.sampler.buckets, max(1, len(self.prompt_buckets))
        shapes = len(buckets) * lengths
        _allow_recompiles(shapes)
        compilations = 2 * (int(1 in buckets) + int(any(b > 1 for b in buckets)))
        if log_progress:
            log.info(
                "compiling the static sampler's two layer functions: %d compilation(s) (bucket 1 apart; batch and prompt "
                "lengths dynamic), then %d shapes run once (%d batch buckets x %d prompt lengths)", compilations, shapes, len(buckets), lengths,
            )  # fmt: skip
        for bucket in reversed(buckets):
            start = time.perf_counter()
            self.on_device(self._compile_bucket, bucket)
            if log_progress:
                log.info("static sampler compiled for bucket %d in %.1f s", bucket, time.perf_counter() - start)

    def _record_graphs(self, log_progress: bool) -> None:
        """Record every bucket's graph. A recording that fails is refused with ``cuda_graphs=on``;
        with ``auto`` the static sampler serves unrecorded (the same chunks, launched eagerly) and
        the log and the description say why."""
        assert self.sampler is not None
        bucket, split_failed = None, False
        try:
            for bucket in reversed(self.sampler.buckets):
                seconds = self.on_device(self._capture, bucket)
                if log_progress:
                    log.info("CUDA graphs of bucket %d recorded in %.1f s (%d prompt lengths)", bucket, seconds, max(1, len(self.prompt_buckets)))
        except Exception as exc:
            if self.sampler.vision is not None:  # the split is an extra: record one graph a bucket instead
                log.warning("recording bucket %s's vision tower apart failed (%s); recording each bucket as one graph", bucket, first_line(exc))
                split_failed = True
            else:
                why = f"recording the CUDA graph of bucket {bucket} failed: {first_line(exc)}"
                if self.engine_options.cuda_graphs == "on":
                    raise ConfigError("engine.cuda_graphs", why) from exc
                self.sampler.drop_graphs()
                self.graphs_wanted, self.sampler_note = False, why
                log.warning("%s; serving with the static sampler unrecorded (--engine.cuda_graphs=on refuses instead)", why)
        if split_failed:  # out of the except block: its traceback no longer holds the failed recording's memory
            self.sampler.drop_graphs()
            self.sampler.vision = self.sampler.rest = None
            self._free_device_memory()
            self._record_graphs(log_progress)

    def _free_device_memory(self) -> None:
        """Return what dropped graphs and tensors held to the device (a retry needs it)."""
        import gc

        import torch

        gc.collect()
        if torch.device(self.device).type == "cuda":
            torch.cuda.empty_cache()

    def _compile_bucket(self, bucket: int) -> None:
        """Compile one bucket's shapes (on the device thread), under the mode batches run in."""
        import torch

        with torch.inference_mode():
            for inputs in self._example_inputs(bucket):
                self.sampler.compile_shape(inputs)

    def _capture(self, bucket: int) -> float:
        """Record the CUDA graph of one bucket (on the device thread) from an example batch, one
        per prompt length."""
        import torch

        with torch.inference_mode():
            return sum(self.sampler.capture(inputs) for inputs in self._example_inputs(bucket))

    def _example_inputs(self, bucket: int) -> list[Any]:
        """The static sampler's inputs for an example batch of ``bucket`` rows, one per prompt
        length, longest first (like the buckets: the shorter prompts' graphs reuse its memory)."""
        import torch

        obs = [self.example_observation(seed=k) for k in range(bucket)]
        with torch.inference_mode():  # as a served batch's inputs are made (see _infer)
            batch = self.to_batch(obs)
            batch["task"] = ["capture"] * bucket
            kwargs = self._forward_kwargs(bucket, None, self.example_prefixes(bucket) if self.rtc_options is not None else None)
            processed = self.preprocessor(batch)
            lengths = reversed(self.prompt_buckets) if self.prompt_buckets else [None]
            return [self._sampler_inputs(processed, kwargs, length) for length in lengths]

    def _sizes(self, max_batch_size: int) -> list[int]:
        """The batch sizes that cost differently: the static sampler's buckets, else 1..cap."""
        if self.sampler is not None and self.sampler.buckets:
            return [b for b in self.sampler.buckets if b <= max_batch_size]
        return list(range(1, max_batch_size + 1))

    def profile(self, max_batch_size: int, warmup: int = 2, reps: int = 5, log_progress: bool = True) -> LatencyProfile:
        """Measure ``d_infer(b)`` for b = 1..max_batch_size (median of ``reps`` after ``warmup``
        untimed passes per size; 0 after :meth:`warmup`). With RTC every timed batch is a guided
        one, so the scheduler plans with RTC's cost. With the static sampler only the buckets
        are measured, and every b gets its bucket's time (b = 3 costs what b = 4 costs).

        Measured medians are made non-decreasing (a larger batch is never cheaper to schedule
        for), as the schedulers require.
        """
        from lerobot_armory.engine.cuda_graphs import bucket_for

        sizes = self._sizes(max_batch_size)
        # At the full prompt length: the scheduler must plan for the longest prompt a robot may send.
        self._prompt_forced = self.prompt_buckets[-1] if self.prompt_buckets else None
        try:
            for _ in range(warmup):
                self._time_sizes(sizes, 1, "", False)
            measured = self._time_sizes(sizes, reps, "profiled", log_progress, statistics.median)
        finally:
            self._prompt_forced = None
        values: list[float] = []
        for b in range(1, max_batch_size + 1):
            ms = measured[bucket_for(b, tuple(sizes)) or b]
            values.append(max(ms, values[-1]) if values else ms)
        # A guided profile says so: RTC's guidance is part of every served batch's time.
        name = f"profiled:{self.config.type}" + ("+rtc" if self.rtc is not None else "")
        return LatencyProfile(name, tuple(values), self.device, "profiled")

    def _time_sizes(
        self, sizes: Sequence[int], reps: int, what: str, log_progress: bool, stat: Callable[[list[float]], float] = min
    ) -> dict[int, float]:
        """``stat`` of ``reps`` timed batches (ms) for each batch size of ``sizes``."""
        out: dict[int, float] = {}
        for b in sizes:
            obs = [self.example_observation(seed=k) for k in range(b)]
            prefixes = self.example_prefixes(b) if self.rtc is not None else None  # RTC's cost is in the profile
            times = []
            for _ in range(max(1, reps)):
                start = time.perf_counter()
                if prefixes is None:
                    self.infer(obs, [what or "warm-up"] * b)
                else:
                    self.infer_guided(obs, [what or "warm-up"] * b, None, prefixes)
                times.append((time.perf_counter() - start) * 1000.0)
            out[b] = stat(times)
            if log_progress:
                log.info("%s b=%d: %.1f ms%s", what, b, out[b], f" ({stat.__name__} of {len(times)})" if len(times) > 1 else "")
        return out


def _early_upload_ok(preprocessor: Any) -> bool:
    """True if the pre-processor has a device step and every step before it is device-agnostic."""
    for step in getattr(preprocessor, "steps", []):
        name = getattr(type(step), "_registry_name", None)
        if name == "device_processor":
            return True
        if name not in DEVICE_AGNOSTIC_STEPS:
            return False
    return False


def _known_steps_only(preprocessor: Any) -> bool:
    """True if every step of the pre-processor is one of LeRobot's own known steps: none changes an
    image tensor in place (it returns the same object, untouched, or a new one), which lets
    ``BucketedSampler.start`` tell by identity that the images it ran on are the batch's, and none
    touches the prompt's mask after the device step (``prompt_columns``)."""
    allowed = DEVICE_AGNOSTIC_STEPS | {"device_processor"}
    steps = getattr(preprocessor, "steps", None)
    return bool(steps) and all(
        getattr(type(step), "_registry_name", None) in allowed and type(step).__module__.startswith("lerobot.") for step in steps
    )


def _noise_shape(policy: Any) -> tuple[int, int] | None:
    """``(H, D)`` of the initial noise of a flow-matching policy whose ``predict_action_chunk``
    forwards ``noise=`` to its ``sample_actions`` (π0, π0.5, SmolVLA); None for other policies."""
    sample = getattr(getattr(policy, "model", None), "sample_actions", None)
    if sample is None:
        return None
    try:
        if "noise" not in inspect.signature(sample).parameters:
            return None
        params = inspect.signature(policy.predict_action_chunk).parameters.values()
    except (TypeError, ValueError):
        return None
    if not any(p.name == "noise" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    h, d = getattr(policy.config, "chunk_size", None), getattr(policy.config, "max_action_dim", None)
    return (h, d) if isinstance(h, int) and isinstance(d, int) else None


def _compiled_functions(policy: Any) -> list[tuple[Any, str, Any]]:
    """``(owner, attribute, compiled fn)`` for every ``torch.compile`` wrapper a policy installed on
    itself or its model (π0.5 compiles ``model.sample_actions`` with ``compile_model=true``)."""
    out = []
    for owner in (policy, getattr(policy, "model", None)):
        if owner is None:
            continue
        for name, value in list(vars(owner).items()):
            if callable(value) and hasattr(value, "_torchdynamo_orig_callable"):
                out.append((owner, name, value))
    return out


def _register_cuda_guard_here() -> None:
    """Without a CUDA device, torch's fake tensors (what torch.compile traces with) register a
    no-op CUDA device guard the first time they run, apparently in the running thread's storage.
    An engine compiles on its own device thread: once that engine was dropped, the next engine's
    compilation crashed the process (a segmentation fault; torch 2.11's CUDA wheel on a machine
    without a GPU). Registered by the thread that builds the engine, it outlives device threads."""
    import torch

    if not torch.cuda.is_available():
        ensure = getattr(torch._C, "_ensureCUDADeviceGuardSet", None)
        if ensure is not None:
            ensure()


def _allow_recompiles(shapes: int) -> None:
    """Each of ``shapes`` input shapes (batch sizes, prompt lengths) may compile its own graph:
    raise dynamo's recompile limit to fit them (with room for a guided and an unguided variant)."""
    import torch._dynamo

    cfg = torch._dynamo.config
    for knob in ("recompile_limit", "cache_size_limit", "accumulated_recompile_limit", "accumulated_cache_size_limit"):
        if hasattr(cfg, knob):
            setattr(cfg, knob, max(getattr(cfg, knob), 2 * shapes + 8))


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

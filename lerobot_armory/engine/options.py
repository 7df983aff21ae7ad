"""The engine's options: ``--policy.*``, ``--engine.*`` and ``--rtc.*``, each validated by itself.

The server's whole configuration (:mod:`lerobot_armory.serving.config`) holds these beside its own
and validates them all once, at start-up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lerobot_armory.errors import ConfigError

@dataclass
class PolicyOptions:
    """``--policy.*`` options.

    Attributes:
        path: local policy directory or hub id (``lerobot/pi05_libero``).
        device: torch device (``cuda``, ``cuda:1``, ``cpu``, ``mps``); default: cuda if available.
        cpu_threads: torch intra-op threads when the policy runs on the CPU; default: all cores
            but one, so the network threads keep a core (oversubscribing makes every batch slower).
        overrides: fields of the policy's own config, as LeRobot takes them after
            ``--policy.path`` (``["dtype=bfloat16", "num_inference_steps=5"]``); on the command
            line every ``--policy.<field>=value`` that is not one of the options above.
    """

    path: str = ""
    device: str | None = None
    cpu_threads: int | None = None
    overrides: list[str] = field(default_factory=list)


@dataclass
class EngineOptions:
    """``--engine.*`` options.

    Attributes:
        emulate_profile: a built-in profile name or JSON file; the engine then takes exactly
            ``d_infer(b)`` per batch (the real model must be faster than that).
        cuda_graphs: ``auto`` (on for a CUDA device and a policy with a static sampler: π0.5, π0, SmolVLA),
            ``on`` (refuse to start without them) or ``off`` (LeRobot's own eager sampler). With
            graphs, batches are padded to buckets and each bucket is one recorded CUDA graph
            (``engine/cuda_graphs.py``); a policy that cannot be captured is served eagerly and
            the start-up log says why.
        graph_buckets: the bucket sizes, comma-separated (default: every size up to 16, then
            multiples of 8 up to ``--max_batch_size``, and the cap itself: on an H200 a padded
            row of π0.5 costs as much as a real one, a bucket costs ≈ 1 s to record and no
            measurable memory, docs/results/gpu).
        prompt_buckets: the static sampler's prompt lengths: LeRobot pads every π0.5 prompt to
            200 tokens and a LIBERO prompt (task and discretised state) uses a few dozen, so a
            batch is cut to the smallest of these lengths that holds its longest prompt (masked
            columns only: the same chunks) — ≈ a fifth of the prefix's arithmetic for a short
            prompt; SmolVLA pads a batch to its longest prompt, so its batches are padded (masked)
            to a length too, one a graph was recorded for. ``auto`` (64 and 128 for π0.5's 200
            tokens, 16 and 32 for π0's and SmolVLA's 48; and the full length), ``off`` (the full
            length only), or token counts like ``64,128`` (multiples of 8 keep π0's and π0.5's
            prefix attention on a GPU's fastest products). Each length is one more CUDA graph per
            batch bucket; ``d_infer(b)`` is profiled at the full length (the scheduler plans for
            the longest prompt).
        static_sampler: run the static sampler without graphs (on a CPU, say: the same chunks,
            fewer operations); unset: wherever graphs are on.
        attention: the static sampler's attention: ``eager`` (LeRobot's own math) or ``sdpa``
            (``torch.nn.functional.scaled_dot_product_attention``).
        fused_kernels: the static sampler runs each transformer layer with fewer kernels (one
            projection for q/k/v and one for the MLP's gate/up, whose weights become views of one
            tensor each; one-kernel RMSNorm with the time conditioning folded into its weight and
            the next projection's bias; q, k and v rotated together, keys and values stored
            straight into the cache; residuals as ``addcmul``; the residual stream in float32):
            a third of the kernels LeRobot's π0.5 sample launches, the same values in another
            rounding order in float32 and, in bfloat16, chunks about as near a float32 model's as
            LeRobot's own bf16 ones, nearer on π0.5 (``acceleration/pi05_kernels.py``). ``false``: LeRobot's own
            sequence of operations (and its bf16 rounding).
        compile_sampler: ``torch.compile`` (inductor) the static sampler's two layer functions,
            a VLM layer and an action-expert layer, before its graphs are recorded: fused
            kernels, fewer of them. One compilation serves every layer of a kind, so it traces
            one layer, not the model's depth; the batch and prompt dimensions are dynamic, so
            warm-up compiles each twice (bucket 1, and every other bucket at every prompt length
            together): 30 s in all for the narrow π0.5 on a 2-core CPU, where the whole sampler
            took 608 s for one compilation. The graphs of each bucket and prompt length are
            recorded from those kernels.
        matmul_precision: float32 matrix products (``torch.set_float32_matmul_precision``, for the
            whole process): ``highest`` (true float32, LeRobot's numerics), ``high`` (TF32 on a
            GPU that has it) or ``auto`` (``high`` for a bfloat16 policy on a CUDA device, else
            ``highest``). With ``--policy.dtype=bfloat16`` LeRobot still runs the SigLIP tower,
            the projector, the norms and the action/time projections in float32; TF32 keeps 10
            mantissa bits, more than the 7 of the bf16 the rest of such a model runs in, and made
            π0.5 1.3–1.6× faster on an H200 (docs/results/gpu).
        vision_dtype: the static sampler's SigLIP tower and projector (π0.5, π0): ``float32``
            (LeRobot's: it keeps them in float32 even in a bfloat16 π0.5, a training concern),
            ``bfloat16`` (half their memory, bf16 matrix units, as openpi's JAX model runs them;
            the weights are cast once at load) or ``auto`` (``bfloat16`` for a bfloat16 policy
            served by the static sampler on a CUDA device, else ``float32``). The full π0.5 on
            an H200: 1.05× faster at b = 1, 1.16× at b = 8, chunks 8.2e-4 from a float32
            π0.5's against 7.0e-4 with the tower in float32 (LeRobot's own bf16: 1.6e-2).
        early_vision: with CUDA graphs, record each bucket's vision tower (image preprocessing,
            SigLIP, projector) as a graph of its own and replay it as soon as the batch's images
            are on the device, so that the GPU runs it while the host runs the pre-processor (the
            tokenizer, π0.5's state prompt, the noise): the same chunks, the host's work before
            the pass hidden behind the tower's. ``false``: one graph a bucket and prompt length,
            replayed after the pre-processor (the GPU waits for it).
    """

    emulate_profile: str | None = None
    cuda_graphs: str = "auto"
    graph_buckets: str | None = None
    prompt_buckets: str = "auto"
    static_sampler: bool | None = None
    attention: str = "eager"
    fused_kernels: bool = True
    compile_sampler: bool = False
    matmul_precision: str = "auto"
    vision_dtype: str = "auto"
    early_vision: bool = True

    def __post_init__(self) -> None:
        # The command-line parser reads YAML, where on/off are booleans: take them back.
        value = str(self.cuda_graphs).lower()
        self.cuda_graphs = {"true": "on", "false": "off", "yes": "on", "no": "off"}.get(value, value)

    def validate(self) -> None:
        from lerobot_armory.acceleration.pi05_static import ATTENTION
        from lerobot_armory.engine.cuda_graphs import MODES

        if self.cuda_graphs not in MODES:
            raise ConfigError("engine.cuda_graphs", f"must be one of {', '.join(MODES)}, got {self.cuda_graphs!r}")
        if self.attention not in ATTENTION:
            raise ConfigError("engine.attention", f"must be one of {', '.join(ATTENTION)}, got {self.attention!r}")
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ConfigError("engine.matmul_precision", f"must be one of {', '.join(MATMUL_PRECISIONS)}, got {self.matmul_precision!r}")
        if self.vision_dtype not in VISION_DTYPES:
            raise ConfigError("engine.vision_dtype", f"must be one of {', '.join(VISION_DTYPES)}, got {self.vision_dtype!r}")
        if self.cuda_graphs == "on" and self.static_sampler is False:
            raise ConfigError("engine.static_sampler", "CUDA graphs record the static sampler: it cannot be off with --engine.cuda_graphs=on")

    def resolved_matmul_precision(self, device: str, dtype: str | None) -> str:
        """``torch.set_float32_matmul_precision``'s argument for a policy of ``dtype`` on ``device``."""
        if self.matmul_precision != "auto":
            return self.matmul_precision
        return "high" if device.startswith("cuda") and dtype == "bfloat16" else "highest"

    def resolved_vision_dtype(self, device: str, dtype: str | None, static: bool) -> str:
        """The vision tower's dtype for a policy of ``dtype`` on ``device`` (``static``: the static
        sampler serves it; only it casts the tower)."""
        if self.vision_dtype != "auto":
            return self.vision_dtype
        return "bfloat16" if static and device.startswith("cuda") and dtype == "bfloat16" else "float32"


MATMUL_PRECISIONS = ("auto", "highest", "high", "medium")
VISION_DTYPES = ("auto", "float32", "bfloat16")


SCHEDULES = ("ZEROS", "ONES", "LINEAR", "EXP")


@dataclass
class RTCOptions:
    """``--rtc.*``: real-time chunking from the mirror (LeRobot's ``RTCConfig`` fields).

    Attributes:
        enabled: guide every chunk toward what its robot executes meanwhile.
        execution_horizon: how far into the new chunk the guidance reaches (steps); LeRobot's
            default. Capped per robot by the length of what it would execute.
        max_guidance_weight: clamp of the guidance weight (LeRobot's ``max_guidance_weight``).
        prefix_attention_schedule: how the guidance fades after the delay: ZEROS (only the
            delayed steps), ONES (full to the horizon), LINEAR or EXP (fading to the horizon).
        delay_margin: steps added to the mirror's predicted delay before it reaches the guidance.
            The action the robot switches at is then held to what it was going to execute
            anyway even when the switch comes a step later than predicted (jitter); an
            underestimate leaves the switch in the fading part, where short chunks have little
            weight, an overestimate only holds one more action (``docs/results/rtc``). LeRobot's
            own engine is conservative the same way (the ceiling of the worst recent latency).
    """

    enabled: bool = False
    execution_horizon: int = 10
    max_guidance_weight: float = 10.0
    prefix_attention_schedule: str = "LINEAR"
    delay_margin: int = 1

    def validate(self) -> None:
        if self.execution_horizon < 1:
            raise ConfigError("rtc.execution_horizon", f"must be >= 1, got {self.execution_horizon}")
        if self.delay_margin < 0:
            raise ConfigError("rtc.delay_margin", f"must be >= 0, got {self.delay_margin}")
        if not self.max_guidance_weight > 0:
            raise ConfigError("rtc.max_guidance_weight", f"must be > 0, got {self.max_guidance_weight}")
        if self.prefix_attention_schedule.upper() not in SCHEDULES:
            raise ConfigError("rtc.prefix_attention_schedule", f"must be one of {', '.join(SCHEDULES)}, got {self.prefix_attention_schedule!r}")

    def lerobot_config(self) -> Any:
        """The equivalent ``lerobot.policies.rtc.RTCConfig``."""
        from lerobot.configs import RTCAttentionSchedule
        from lerobot.policies.rtc.configuration_rtc import RTCConfig

        return RTCConfig(
            enabled=True,
            prefix_attention_schedule=RTCAttentionSchedule[self.prefix_attention_schedule.upper()],
            max_guidance_weight=float(self.max_guidance_weight),
            execution_horizon=int(self.execution_horizon),
        )

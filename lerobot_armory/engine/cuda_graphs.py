"""Batch buckets and one CUDA graph per bucket for a static sampler.

A CUDA graph replays a recorded sequence of kernels with the tensor addresses and shapes it was
recorded with, for the cost of one launch. The static sampler (``acceleration/pi05_static.py``) is
such a sequence for each batch size, so the engine records one graph per *bucket* (default
1, 2, 4, 8, …, up to the batch cap, and the cap itself) and serves a batch of b robots with the
graph of the smallest bucket ≥ b: the real rows are copied into the graph's input buffers, the
rows behind them repeat the last real row (rows never mix, so padding cannot change a real
row's chunk), the graph is replayed, and the real rows of its output are returned.

The scheduler plans with ``d_infer(b)`` = the measured time of b's bucket (``PolicyEngine.profile``
measures the buckets), so it knows that b = 3 costs what b = 4 costs.

Prompt buckets: LeRobot pads every π0.5 prompt to 200 tokens, and a LIBERO prompt (task and
discretised state) uses a few dozen: the rest is masked arithmetic, ≈ a fifth of the prefix. The
engine fits a batch's prompt columns to the smallest *prompt bucket* that holds its longest
prompt (``--engine.prompt_buckets``), so one graph is recorded per (batch bucket, prompt bucket).
Fitting also pads: SmolVLA's tokenizer pads a batch to its longest prompt, a new length nearly
every batch, which no recorded graph would fit.

The vision tower apart: a bucket records its vision graph (the images' preprocessing, SigLIP,
the projector) and, per prompt length, the rest, which reads the vision graph's output in place.
The engine replays the vision graph as soon as a batch's images are on the device
(:meth:`BucketedSampler.start`), before its pre-processor tokenizes the prompts on the host: the
GPU no longer waits for that host work before every pass.

Capture rules followed here (PyTorch's ``torch.cuda.graphs`` notes): every bucket is warmed up on
a side stream before it is recorded, and recorded on that same stream (lazy initialisations and
per-stream cuBLAS workspaces happen there, not in the recording); all buckets share one memory
pool and that stream, recorded from the largest down so the smaller ones reuse its blocks;
everything — capture and every replay — runs on the engine's one device thread; inputs are copied
into the recorded buffers and the output is copied out before the next replay can overwrite it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lerobot_armory.errors import ConfigError
from lerobot_armory.acceleration.pi05_static import SamplerInputs

log = logging.getLogger(__name__)

MODES = ("auto", "on", "off")
DENSE_BUCKETS = 16  # every batch size up to this one is its own bucket by default


def parse_buckets(text: str | None, max_batch_size: int) -> tuple[int, ...]:
    """The bucket sizes for a batch cap: ``text`` (``"1,2,4,8"``) or every size up to 16, then
    multiples of 8, always ending at the cap (sizes above it are dropped: no batch is ever that
    large). Every small size has its own bucket because a padded row costs what a real one does
    (π0.5 on an H200: ≈ 10 ms a row, linear from b = 2) while a bucket costs ≈ 1 s to record
    and shares the graphs' memory pool.

    Raises:
        ConfigError: a size that is not a positive integer.
    """
    if max_batch_size < 1:
        raise ConfigError("max_batch_size", f"must be >= 1, got {max_batch_size}")
    if text is None or not text.strip():
        sizes = set(range(1, min(max_batch_size, DENSE_BUCKETS) + 1)) | set(range(DENSE_BUCKETS + 8, max_batch_size + 1, 8))
    else:
        try:
            sizes = {int(s) for s in text.split(",") if s.strip()}
        except ValueError:
            raise ConfigError("engine.graph_buckets", f"must be comma-separated batch sizes like 1,2,4,8, got {text!r}") from None
        if not sizes or min(sizes) < 1:
            raise ConfigError("engine.graph_buckets", f"sizes must be >= 1, got {text!r}")
    return tuple(sorted({s for s in sizes if s <= max_batch_size} | {max_batch_size}))


# ``auto``'s lengths below the policy's full prompt length (always a bucket too): for a long prompt
# (π0.5 pads to 200 tokens; a LIBERO task and discretised state use a few dozen), 64 and 128; for a
# short one (π0's and SmolVLA's 48; a LIBERO task alone is 10–20 tokens), 16 and 32.
AUTO_PROMPT_BUCKETS_LONG = (64, 128)
AUTO_PROMPT_BUCKETS_SHORT = (16, 32)
SHORT_PROMPT = 64  # a full length up to this is short


def parse_prompt_buckets(text: str, full: int) -> tuple[int, ...]:
    """The prompt lengths a batch is fitted to, ascending, ending at ``full`` (the tokenizer's max
    length): ``auto`` (those of 64 and 128 tokens below ``full``; 16 and 32 when ``full`` is at
    most 64), ``off`` (none: every batch has ``full`` columns) or comma-separated lengths. Empty
    when nothing is below ``full``.

    Raises:
        ConfigError: a length that is not an integer in 1..full.
    """
    word = text.strip().lower()
    if word in ("off", "none", "false", "no"):
        return ()
    if word == "auto":
        sizes = set(AUTO_PROMPT_BUCKETS_SHORT if full <= SHORT_PROMPT else AUTO_PROMPT_BUCKETS_LONG)
    else:
        try:
            sizes = {int(s) for s in word.split(",") if s.strip()}
        except ValueError:
            raise ConfigError("engine.prompt_buckets", f"must be auto, off or comma-separated token counts like 64,128, got {text!r}") from None
        if not sizes or min(sizes) < 1 or max(sizes) > full:
            raise ConfigError("engine.prompt_buckets", f"token counts must be in 1..{full} (the policy's prompt length), got {text!r}")
    below = sorted(s for s in sizes if s < full)
    return (*below, full) if below else ()  # the full length alone: nothing to trim


def bucket_for(rows: int, buckets: tuple[int, ...]) -> int | None:
    """The smallest bucket that holds ``rows`` (None: larger than every bucket)."""
    return next((b for b in buckets if b >= rows), None)


@dataclass
class _Graph:
    graph: Any  # torch.cuda.CUDAGraph
    inputs: list[Tensor]  # the recorded input buffers, in SamplerInputs.tensors() order
    output: Any  # a Tensor; a vision graph's: a tuple of them


class BucketedSampler:
    """Runs ``sample`` (a static sampler's ``sample(SamplerInputs) -> Tensor``) on batches padded to
    buckets; with :meth:`capture`, as one CUDA graph per bucket.

    Before :meth:`set_buckets` every batch runs at its own size through ``uncompiled`` (the
    engine's dry run: a compiled ``sample`` would compile a size no bucket has). A batch
    larger than every bucket, or one whose tensors do not have the recorded shapes, runs eagerly
    at its own size, logged once: correct, only slower; :attr:`unrecorded` counts such batches
    (the server's ``armory_batches_unrecorded`` metric), so a slow fleet can be told from a
    slow GPU.

    Given ``vision`` and ``rest`` (``sample`` split in two: ``vision(images)`` → the image part of
    the prefix, ``rest(inputs, vision_output)`` → the actions), each bucket records two graphs: its
    vision graph, and per prompt length the rest, which reads the vision graph's output where it
    lies. :meth:`start` replays a batch's vision graph as soon as its images are on the device, so
    the GPU runs the vision tower while the host tokenizes the prompt; a batch not started (or
    started on other image tensors) replays it at :meth:`__call__`, so the chunks never depend on
    whether it was.
    """

    def __init__(
        self,
        sample: Callable[[SamplerInputs], Tensor],
        prepare: Callable[[], object] | None = None,
        uncompiled: Callable[[SamplerInputs], Tensor] | None = None,
        vision: Callable[[tuple[Tensor, ...]], tuple[Tensor, ...]] | None = None,
        rest: Callable[[SamplerInputs, tuple[Tensor, ...]], Tensor] | None = None,
    ) -> None:
        self.sample = sample
        self.uncompiled = uncompiled or sample
        self.prepare = prepare  # the sampler's constants, made before a shape is traced or recorded
        self.vision, self.rest = (vision, rest) if vision is not None and rest is not None else (None, None)
        self.buckets: tuple[int, ...] = ()
        self.graphs: dict[tuple[int, int], _Graph] = {}  # by (batch bucket, prompt length)
        self.vision_graphs: dict[int, _Graph] = {}  # by batch bucket (split: vision and rest)
        self._started: tuple[int, tuple[Tensor, ...]] | None = None  # the bucket and images start() ran
        self._vision_out: tuple[Tensor, ...] | None = None  # the vision graphs' shared output buffers
        self.early_starts = 0  # batches whose vision graph ran before their prompt was tokenized
        self.capture_s: dict[int, float] = {}  # by batch bucket, all its prompt lengths together
        self._pool: Any = None
        self._stream: Any = None
        self._warned: set[str] = set()
        self.unrecorded = 0  # batches run eagerly although graphs were recorded

    @property
    def captured(self) -> bool:
        return bool(self.graphs)

    def drop_graphs(self) -> None:
        """Forget every recorded graph (a recording failed: the batches run unrecorded)."""
        self.graphs.clear()
        self.vision_graphs.clear()
        self._started = None
        self._vision_out = None

    def set_buckets(self, buckets: tuple[int, ...]) -> None:
        if self.graphs and tuple(buckets) != self.buckets:
            raise RuntimeError("buckets cannot change after capture")
        self.buckets = tuple(buckets)

    def __call__(self, inputs: SamplerInputs) -> Tensor:
        """Actions for the batch's real rows (a new tensor, safe to keep across calls)."""
        rows = inputs.rows
        started, self._started = self._started, None  # a start counts for the call right after it only
        if not self.buckets:
            return self.uncompiled(inputs)  # the uncompiled sampler prepares its own constants
        bucket = bucket_for(rows, self.buckets)
        if bucket is None:
            self._missed("big", f"a batch of {rows} is larger than every bucket {self.buckets}: run eagerly at its own size")
            return self._eager(inputs, rows)
        graph = self.graphs.get((bucket, inputs.prompt_length))
        if graph is None:
            if self.graphs:
                self._missed("prompt", f"no graph for prompts of {inputs.prompt_length} tokens in bucket {bucket}: run eagerly")
            return self._eager(inputs, bucket)
        tensors = inputs.tensors()
        vision = self.vision_graphs.get(bucket)
        images = len(inputs.images) if vision is not None else 0
        if not _fits(tensors[images:], graph.inputs) or (vision is not None and not _fits(tensors[:images], vision.inputs)):
            self._missed("shape", f"inputs {[tuple(t.shape) for t in tensors]} do not fit the graph of bucket {bucket}: run eagerly")
            return self._eager(inputs, bucket)
        if vision is not None:
            if started is not None and started[0] == bucket and _same(started[1], inputs.images):
                self.early_starts += 1
            else:
                _feed(vision.inputs, tensors[:images], rows, bucket)
                vision.graph.replay()
        _feed(graph.inputs, tensors[images:], rows, bucket)
        graph.graph.replay()
        return graph.output[:rows].clone()

    def start(self, images: Sequence[Tensor]) -> bool:
        """Replay the vision graph of the batch's bucket on ``images`` (the tensors its inputs
        will hold, on the device) now, before the host tokenizes its prompt; the batch's
        :meth:`__call__` with the same tensors then skips it. True if started. A no-op without
        vision graphs or for images that fit none."""
        self._started = None
        if not self.vision_graphs or not images or not self.buckets:
            return False
        rows = int(images[0].shape[0])
        bucket = bucket_for(rows, self.buckets)
        vision = self.vision_graphs.get(bucket) if bucket is not None else None
        if vision is None or not _fits(list(images), vision.inputs) or any(int(i.shape[0]) != rows for i in images):
            return False
        _feed(vision.inputs, list(images), rows, bucket)
        vision.graph.replay()
        self._started = (bucket, tuple(images))
        return True

    def compile_shape(self, inputs: SamplerInputs) -> None:
        """Run ``sample`` once on ``inputs`` (a bucket's rows at one prompt length), so that a
        compiled ``sample`` compiles that shape now rather than under the first robots."""
        if inputs.rows not in self.buckets:
            raise ValueError(f"{inputs.rows} is not a bucket ({self.buckets})")
        self._eager(inputs, inputs.rows)

    def _eager(self, inputs: SamplerInputs, bucket: int) -> Tensor:
        if self.prepare is not None:
            self.prepare()
        return self.sample(inputs.padded(bucket))[: inputs.rows]

    def capture(self, example: SamplerInputs, warmup: int = 3) -> float:
        """Record the graph of the bucket ``example.rows`` at ``example``'s prompt length (a CUDA
        device; call from the thread that will replay it); returns the seconds it took.
        ``example``'s values are the first contents of the input buffers."""
        bucket = example.rows
        if bucket not in self.buckets:
            raise ValueError(f"{bucket} is not a bucket ({self.buckets})")
        start = time.perf_counter()
        if self.prepare is not None:
            self.prepare()
        device = example.noise.device
        inputs = [t.clone() for t in example.tensors()]
        static = example.with_tensors(inputs)
        if self.vision is not None and self.rest is not None:
            vision, rest = self.vision, self.rest
            images = len(example.images)
            seen = self.vision_graphs.get(bucket)
            if seen is None:  # once per bucket; every prompt length's rest reads its output
                views = self._vision_views(bucket, static.images)

                def run_vision() -> tuple[Tensor, ...]:
                    for out, new in zip(views, vision(static.images), strict=True):
                        out.copy_(new)
                    return views

                graph, _ = self._record(run_vision, warmup, device)
                seen = self.vision_graphs[bucket] = _Graph(graph, inputs[:images], views)
            else:
                static = static.with_tensors([*seen.inputs, *inputs[images:]])
            vision_output = seen.output
            graph, output = self._record(lambda: rest(static, vision_output), warmup, device)
            self.graphs[(bucket, example.prompt_length)] = _Graph(graph, inputs[images:], output)
        else:
            graph, output = self._record(lambda: self.sample(static), warmup, device)
            self.graphs[(bucket, example.prompt_length)] = _Graph(graph, inputs, output)
        torch.cuda.synchronize(device)
        seconds = time.perf_counter() - start
        self.capture_s[bucket] = self.capture_s.get(bucket, 0.0) + seconds
        return seconds

    def _vision_views(self, bucket: int, images: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
        """The first ``bucket`` rows of the buffers every bucket's vision graph writes its output
        into and every rest reads it from: one set, sized for the largest bucket, allocated
        outside the graphs' pool (each bucket's own outputs would stay allocated for good, ≈ 2 MiB
        a camera and row). Safe to share: graphs replay one at a time on one thread and stream,
        and a bucket's rest reads them right after its own vision graph wrote them."""
        if self._vision_out is None:
            example = self.vision(images)  # type: ignore[misc]  # shapes and dtypes, eagerly, before any recording
            rows = max(self.buckets)
            self._vision_out = tuple(torch.empty((rows, *t.shape[1:]), dtype=t.dtype, device=t.device) for t in example)
        return tuple(buf[:bucket] for buf in self._vision_out)

    def _record(self, fn: Callable[[], Any], warmup: int, device: Any) -> tuple[Any, Any]:
        """Warm ``fn`` up on the side stream, record it as a CUDA graph in the shared pool, replay
        it once (its output then holds real values); returns (graph, output)."""
        if self._pool is None:
            self._pool = torch.cuda.graph_pool_handle()
            # One side stream for every warm-up and every recording: handles and workspaces that
            # libraries create per stream on first use then exist before a recording starts, and
            # graphs sharing a pool should be recorded on the same stream (PyTorch's note).
            self._stream = torch.cuda.Stream(device)
        side = self._stream
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                fn()
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self._pool, stream=side):
            output = fn()
        graph.replay()
        return graph, output

    def _missed(self, key: str, message: str) -> None:
        """A batch runs without its bucket's graph: each reason logged once, and the batch counted
        once graphs exist (before capture every batch runs so)."""
        if self.graphs:
            self.unrecorded += 1
            message += " (each such batch is counted in armory_batches_unrecorded)"
        self._warn_once(key, message)

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning("%s", message)


def _feed(buffers: Sequence[Tensor], tensors: Sequence[Tensor], rows: int, bucket: int) -> None:
    """Copy a batch's rows into a graph's input buffers; the rows behind them repeat its last
    row (rows never mix, so padding cannot touch a real one)."""
    for buf, src in zip(buffers, tensors, strict=True):
        buf[:rows].copy_(src)
        if rows < bucket:
            buf[rows:].copy_(src[-1:].expand(bucket - rows, *src.shape[1:]))


def _same(a: Sequence[Tensor], b: Sequence[Tensor]) -> bool:
    """The same tensor objects, in order (what :meth:`BucketedSampler.start` ran on)."""
    return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))


def _fits(tensors: list[Tensor], recorded: list[Tensor]) -> bool:
    return len(tensors) == len(recorded) and all(
        t.shape[1:] == r.shape[1:] and t.dtype == r.dtype and t.device == r.device for t, r in zip(tensors, recorded, strict=True)
    )


"""What a forward pass asks of the device, seen from a CPU: aten ops counted, host syncs found.

On a GPU every aten op that computes something is (at least) one kernel launch, and an eager
policy that launches thousands of small kernels per sample is bound by the launches, not the
arithmetic. A CUDA graph removes the launch cost, but it can only record a region that never
waits for the host: no ``.item()``, no tensor built from Python data (``torch.tensor(list,
device=...)`` is a blocking host-to-device copy), no device-to-host copy, no op whose output
shape depends on values (``nonzero``). :class:`OpTrace` records every aten op a region runs
(under ``TorchDispatchMode``, so it works on the CPU, with no GPU), counts those that launch work,
and names the ones that would synchronise with the host — the check that predicts whether a
capture on a GPU can succeed (together with a ``torch.compile(fullgraph=True)`` trace).

Counting kernels from a CPU has two traps:
- under ``torch.inference_mode`` composite ops (``matmul``, ``linear``, ``reshape``) reach the
  trace whole, hiding the copies they make of non-contiguous inputs; run the region under
  ``torch.no_grad`` and they arrive decomposed (``mm``, ``bmm``, ``clone``), as a GPU runs them;
- an op can be one kernel on CUDA and a composite on the CPU: ``rms_norm`` is CUDA's
  ``_fused_rms_norm`` kernel (torch ≥ 2.8) but five ops here. :data:`ONE_KERNEL_ON_CUDA` lists
  such functions; each call counts as one launch when this torch build has the CUDA kernel
  (the same in either mode).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

# Ops that only describe memory (no kernel): views, aliases and metadata.
VIEW_OPS = frozenset(
    {
        "view", "_unsafe_view", "reshape", "t", "transpose", "permute", "unsqueeze", "squeeze", "expand",
        "slice", "select", "as_strided", "alias", "detach", "split", "split_with_sizes", "chunk", "unbind",
        "narrow", "view_as", "expand_as", "_reshape_alias", "unflatten", "flatten",
        "empty", "empty_strided", "empty_like", "new_empty", "new_empty_strided", "_to_copy_noop",
    }
)  # fmt: skip
# Ops that wait for the host or read a value back to it (illegal inside a CUDA graph capture).
HOST_SYNC_OPS = frozenset(
    {
        "_local_scalar_dense", "item", "lift_fresh", "lift_fresh_copy", "nonzero", "masked_select", "unique", "_unique",
        "_unique2", "unique_consecutive", "unique_dim", "equal", "is_nonzero", "_assert_async", "repeat_interleave",
        "tolist", "argwhere",
    }
)  # fmt: skip




def _one_kernel_on_cuda() -> dict[Any, str]:
    """Functions that CUDA runs as one kernel where this CPU runs several: function -> the CUDA op."""
    out = {}
    if torch._C._dispatch_has_kernel_for_dispatch_key("aten::_fused_rms_norm", "CUDA"):
        out[torch.nn.functional.rms_norm] = "aten._fused_rms_norm.default"
    return out


ONE_KERNEL_ON_CUDA = _one_kernel_on_cuda()


def op_name(func: Any) -> str:
    """``aten.add.Tensor`` -> ``add``."""
    return str(func).split(".")[1] if str(func).count(".") >= 1 else str(func)


class OpTrace(TorchDispatchMode):
    """Counts the aten ops run inside ``with OpTrace() as trace:``.

    Attributes:
        ops: every op's full name with its count.
        launches: ops that compute something: an estimate of the kernels a GPU would launch.
            Views, allocations and ops that hand back their input unchanged (``x.to(x.dtype)``,
            ``x.contiguous()`` of a contiguous x) are not counted; in-place ops are.
        host_syncs: ``(op, count)`` of the ops that would synchronise with the host: reading a
            value back, building a tensor from Python data, a data-dependent output shape, or a
            copy between devices.
    """

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()
        self.launched: Counter[str] = Counter()
        self.host_syncs: Counter[str] = Counter()
        self._inside_fused = 0  # > 0: inside a function CUDA runs as one kernel (already counted)
        self._functions = _FusedOnCuda(self)

    def __enter__(self) -> OpTrace:
        self._functions.__enter__()
        return super().__enter__()

    def __exit__(self, *exc: Any) -> None:
        super().__exit__(*exc)
        self._functions.__exit__(*exc)

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        name = op_name(func)
        if name in HOST_SYNC_OPS:
            self.host_syncs[str(func)] += 1
        out = func(*args, **kwargs)
        if name in ("_to_copy", "copy_", "to") and _crosses_devices(args, out):
            self.host_syncs[f"{func} (between devices)"] += 1
        if self._inside_fused:
            return out
        self.ops[str(func)] += 1
        if name not in VIEW_OPS and (name.endswith("_") or not _returns_an_input(out, args)):
            self.launched[str(func)] += 1
        return out

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def launches(self) -> int:
        return sum(self.launched.values())

    def top(self, n: int = 8) -> list[tuple[str, int]]:
        """The ``n`` most frequent launching ops."""
        return self.launched.most_common(n)


def _returns_an_input(out: Any, args: tuple) -> bool:
    """True if ``out`` is one of the input tensors (or a view of one): no new data was computed."""
    if not isinstance(out, torch.Tensor):
        return False
    ptr = out.untyped_storage().data_ptr()
    return any(isinstance(a, torch.Tensor) and a.untyped_storage().data_ptr() == ptr for a in args)


def _crosses_devices(args: tuple, out: Any) -> bool:
    devices = {a.device for a in args if isinstance(a, torch.Tensor)}
    if isinstance(out, torch.Tensor):
        devices.add(out.device)
    return len(devices) > 1


class _FusedOnCuda(TorchFunctionMode):
    """Counts a call of a :data:`ONE_KERNEL_ON_CUDA` function as the one kernel CUDA launches, and
    keeps the ops it runs here out of the count."""

    def __init__(self, trace: OpTrace) -> None:
        super().__init__()
        self.trace = trace

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        cuda_op = ONE_KERNEL_ON_CUDA.get(func)
        if cuda_op is None or self.trace._inside_fused:
            return func(*args, **kwargs)
        self.trace.ops[cuda_op] += 1
        self.trace.launched[cuda_op] += 1
        self.trace._inside_fused += 1
        try:
            return func(*args, **kwargs)
        finally:
            self.trace._inside_fused -= 1

"""What an engine's exception says about the device: one batch's problem, too big a batch, or a lost device.

The serving loop acts on the answer:

- ``OUT_OF_MEMORY``: the batch did not fit (``torch.OutOfMemoryError``, CUDA's or the CPU
  allocator's). A smaller batch may: the loop lowers the batch cap below that size and serves the
  same robots again in smaller batches; they see a delay, not an error. At batch size 1 nothing
  smaller exists, and it is a failed batch like any other.
- ``DEVICE_LOST``: the CUDA context is unusable (an illegal memory access, a device-side assert,
  a launch failure, the GPU fell off the bus). Every later batch fails too; the loop stops at
  once and the server exits non-zero with one line, so that a supervisor (systemd, Kubernetes,
  Ray) restarts it and the robots reconnect.
- ``BATCH``: anything else fails this batch only; its robots are told and served again.
"""

from __future__ import annotations

import enum


class Fault(enum.Enum):
    """How the loop should take an engine's exception."""

    BATCH = "batch"
    OUT_OF_MEMORY = "out_of_memory"
    DEVICE_LOST = "device_lost"


# CUDA errors after which the context cannot run another kernel (CUDA's "sticky" errors), as
# PyTorch words them in the exception text, and what NVIDIA's driver reports when the GPU is gone.
STICKY_CUDA_ERRORS = (
    "illegal memory access",
    "cudaErrorIllegalAddress",
    "device-side assert triggered",
    "unspecified launch failure",
    "cudaErrorLaunchFailure",
    "misaligned address",
    "illegal instruction",
    "hardware stack error",
    "uncorrectable ECC error",
    "GPU is lost",
    "fallen off the bus",
    "cudaErrorDevicesUnavailable",
)
# Out-of-memory messages of allocators that do not raise torch's type (cuBLAS, cuDNN workspaces).
OOM_TEXT = ("CUDA out of memory", "CUBLAS_STATUS_ALLOC_FAILED", "CUDNN_STATUS_ALLOC_FAILED", "out of memory")


def classify(exc: BaseException) -> Fault:
    """The fault an engine's exception stands for (see the module docstring)."""
    text = f"{type(exc).__name__}: {exc}"
    if any(marker.lower() in text.lower() for marker in STICKY_CUDA_ERRORS):
        return Fault.DEVICE_LOST
    # torch.OutOfMemoryError (torch.cuda.OutOfMemoryError is the same class) by name, so that the
    # serving loop, which may run a torch-free engine, never imports torch to ask.
    if any(cls.__name__ == "OutOfMemoryError" for cls in type(exc).__mro__) or isinstance(exc, MemoryError):
        return Fault.OUT_OF_MEMORY
    if any(marker.lower() in text.lower() for marker in OOM_TEXT):
        return Fault.OUT_OF_MEMORY
    return Fault.BATCH

"""Moving a chunk to and from the model's device, and the device's limits, measured.

On a GPU a chunk's frames go up through pinned host memory (``non_blocking``), the attention
runs on a fused kernel (flash or memory-efficient; the math fallback, which materialises the
``N × N`` score matrix of global attention, is refused rather than taken silently), and the
outputs come down in one synchronisation: each output copied into pinned memory
asynchronously, then one wait.  On the CPU every function is the plain operation, so CPU
results do not change.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from swiftjax.errors import SwiftjaxError

if TYPE_CHECKING:
    import torch

__all__ = [
    "DeviceError",
    "GPUMemoryError",
    "check_device",
    "fused_attention",
    "largest_chunk_that_fits",
    "model_math",
    "runner_device",
    "share_gpu_with_jax",
    "to_device",
    "without_autocast",
    "to_host",
]


class GPUMemoryError(SwiftjaxError, ValueError):
    """A chunk does not fit in the device's memory (the message gives the largest that does)."""


class DeviceError(SwiftjaxError, ValueError):
    """A device that is not one, or that this machine or build does not have."""


def share_gpu_with_jax(environ: Any = None) -> bool:
    """Keep JAX from taking the GPU's memory that the model needs; whether it did anything.

    A CUDA build of JAX reserves 75 % of a GPU's memory at its first operation
    (``XLA_PYTHON_CLIENT_PREALLOCATE``), so a geometry call made after the model was put on the
    same GPU would leave torch a quarter of the card, and one made before it would make the
    first chunk fail for want of memory.  This sets ``XLA_PYTHON_CLIENT_PREALLOCATE=false``
    (JAX then allocates what it uses) unless the user set it; it must run before JAX starts
    its backend, which is why the torch runner calls it when it is put on a CUDA device and the
    CLI when it checks ``--device``.  A JAX backend started earlier keeps its pool: the value
    is read once.
    """
    import os

    environ = os.environ if environ is None else environ
    if "XLA_PYTHON_CLIENT_PREALLOCATE" in environ:
        return False
    environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    return True


@contextlib.contextmanager
def without_autocast(device: torch.device) -> Iterator[None]:
    """Full precision inside a reduced-precision forward, for the geometry at the end of a head
    (SVD, determinants, QR, RANSAC fits): torch has no bf16 / fp16 kernels for some of it on
    CUDA (``torch.det`` raises there), and 8 bits of mantissa would ruin the rest.  Tensors
    made inside are float32 when their inputs are; inputs in bf16 must be cast by the caller."""
    import torch

    with torch.autocast(device_type=device.type, enabled=False):
        yield


def runner_device(device: Any) -> torch.device:
    """``torch.device(device)`` for a runner; on CUDA, :func:`share_gpu_with_jax` first."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        share_gpu_with_jax()
    return device


def check_device(text: str, backend: str = "torch", *, name: str = "device") -> Any:
    """The device ``text`` of ``backend`` if this machine can run it; :class:`DeviceError`
    otherwise, its message naming the input as ``name`` (the CLI: ``--device``).

    ``backend="torch"``: a ``torch.device`` of type cpu, cuda (``cuda:N`` with ``N`` below the
    visible count) or mps, the build's support and the hardware probed.  ``backend="onnx"``:
    ``text`` itself, cpu, or cuda with onnxruntime's CUDA provider installed.
    """
    if backend == "onnx":
        if text == "cpu":
            return text
        import onnxruntime as ort

        if not text.startswith("cuda"):
            raise DeviceError(f"{name} {text}: the ONNX backend runs on cpu or cuda")
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise DeviceError(
                f"{name} {text}: onnxruntime has no CUDA provider here "
                f"(has {', '.join(ort.get_available_providers())}; install onnxruntime-gpu)"
            )
        return text
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise DeviceError(f"{name} {text!r} is not a torch device (cpu, cuda, cuda:N, mps)") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise DeviceError(f"{name} {text}: {why} (torch {torch.__version__}); use {name} cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise DeviceError(f"{name} {text}: only {torch.cuda.device_count()} CUDA device(s) are visible")
        share_gpu_with_jax()
    elif device.type == "mps":
        if not torch.backends.mps.is_available():
            raise DeviceError(f"{name} {text}: this torch build or machine has no MPS support; use {name} cpu")
    elif device.type != "cpu":
        raise DeviceError(f"{name} {text}: device type {device.type!r} is not supported (cpu, cuda, mps)")
    return device


def to_device(array: np.ndarray, device: torch.device) -> torch.Tensor:
    """``array`` as a tensor on ``device`` (CUDA: through pinned memory, asynchronously)."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(array))
    if device.type == "cuda":
        return t.pin_memory().to(device, non_blocking=True)
    return t.to(device)


def to_host(tensors: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Every tensor as a float32 NumPy array; on CUDA each is copied into pinned memory
    asynchronously and the stream is synchronised once."""
    import torch

    first = next(iter(tensors.values()), None)
    if first is None or first.device.type != "cuda":
        return {k: v.float().cpu().numpy() for k, v in tensors.items()}
    out = {}
    for k, v in tensors.items():
        buf = torch.empty(v.shape, dtype=torch.float32, pin_memory=True)
        buf.copy_(v, non_blocking=True)
        out[k] = buf
    torch.cuda.current_stream(first.device).synchronize()
    return {k: v.numpy() for k, v in out.items()}


@contextlib.contextmanager
def fused_attention(device: torch.device) -> Iterator[None]:
    """On CUDA, ``scaled_dot_product_attention`` may use the flash or memory-efficient kernel
    only (a shape or dtype neither takes raises instead of falling back to the math path);
    elsewhere torch's own choice."""
    if device.type != "cuda":
        yield
        return
    from torch.nn.attention import SDPBackend, sdpa_kernel

    try:
        with sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION]):
            yield
    except RuntimeError as err:
        if "No available kernel" not in str(err):
            raise
        raise RuntimeError(
            f"no fused attention kernel (flash, memory-efficient) runs this model on {device}: {err}"
        ) from None


@contextlib.contextmanager
def model_math(device: torch.device, dtype: torch.dtype) -> Iterator[None]:
    """How every runner's forward computes: ``inference_mode``; :func:`fused_attention`;
    ``dtype`` float32 means float32 (on CUDA without TF32, for cuDNN's convolutions too, whose
    TF32 torch allows by default: it moved the tiny golden VGGT's depth by 2.6e-3 relative on
    an H200, 26 × the golden's tolerance); a reduced ``dtype`` is ``torch.autocast`` over the
    forward (heads that need full precision leave it themselves: :func:`without_autocast`).
    """
    import torch

    with torch.inference_mode(), fused_attention(device), contextlib.ExitStack() as stack:
        if dtype != torch.float32:
            stack.enter_context(torch.autocast(device_type=device.type, dtype=dtype))
        elif device.type == "cuda":
            saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
            torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False

            def restore() -> None:
                torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved

            stack.callback(restore)
        yield


def largest_chunk_that_fits(run: Callable[[int], Any], frames: int, *, device: torch.device) -> int:
    """The largest chunk size ``S <= frames`` for which ``run(S)`` does not run out of device
    memory, found by trying (halving down from ``frames``, then bisecting between the last size
    that failed and the first that ran); 0 if not even one frame fits."""
    import torch

    def fits(s: int) -> bool:
        try:
            run(s)
            return True
        except torch.OutOfMemoryError:
            return False
        finally:
            if device.type == "cuda":
                torch.cuda.empty_cache()

    hi = frames  # known (or assumed) not to fit
    lo = hi // 2
    while lo >= 1 and not fits(lo):
        hi, lo = lo, lo // 2
    if lo < 1:
        return 0
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo

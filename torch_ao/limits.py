"""Resource limits: what is refused, before anything is allocated, because it cannot fit in memory.

Each limit has a default (and why), and an environment variable that overrides it (a positive
number; read at each check, so set it before or while the process runs):

=====================  =================================  ==================================================
limit                  environment variable               default
=====================  =================================  ==================================================
``image_pixels``       ``TORCH_AO_MAX_IMAGE_PIXELS``      ``2**28`` (16384 x 16384): pixels of one image a
                                                          file declares (.npz member, EXR data window, PNG)
``array_bytes``        ``TORCH_AO_MAX_ARRAY_BYTES``       half the machine's memory: the uncompressed size of
                                                          one file's arrays, summed (a zip bomb, a header
                                                          that claims more than the file can hold)
``walk_bytes``         ``TORCH_AO_MAX_WALK_BYTES``        half the machine's memory: a method call's memory
                                                          estimated from B, H, W, slices and steps
                                                          (:func:`walk_bytes`)
=====================  =================================  ==================================================

"Half the machine's memory" is the physical memory (``os.sysconf``) over two, 8 GiB where it cannot be
read: the rest is left to the program, PyTorch and the other buffers of the run.

A refusal is a :class:`ResourceLimitError` (a ``ValueError``) naming what was refused, its size and the
limit, and the variable that raises it.
"""
from __future__ import annotations

import os

__all__ = ["LIMITS", "ResourceLimitError", "limit", "check_limit", "walk_bytes", "machine_memory"]


def machine_memory() -> int:
    """Physical memory in bytes (8 GiB where the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - platform dependent
        return 8 << 30


#: ``{name: (environment variable, default, unit)}``
LIMITS: dict[str, tuple[str, int, str]] = {
    "image_pixels": ("TORCH_AO_MAX_IMAGE_PIXELS", 1 << 28, "pixels"),
    "array_bytes": ("TORCH_AO_MAX_ARRAY_BYTES", machine_memory() // 2, "bytes"),
    "walk_bytes": ("TORCH_AO_MAX_WALK_BYTES", machine_memory() // 2, "bytes"),
}


class ResourceLimitError(ValueError):
    """Something would need more memory than a limit of :data:`LIMITS` allows."""


def limit(name: str) -> int:
    """The limit ``name`` of :data:`LIMITS`: its environment variable when set, else the default."""
    env, default, _ = LIMITS[name]
    text = os.environ.get(env)
    if text is None or not text.strip():
        return default
    try:
        value = int(float(text))
    except ValueError:
        raise ValueError(f"{env}: expected a positive number, got {text!r}") from None
    if value <= 0:
        raise ValueError(f"{env}: expected a positive number, got {text!r}")
    return value


def _size(value: int, unit: str) -> str:
    if unit == "bytes":
        return f"{value / (1 << 30):.3g} GiB" if value >= 1 << 30 else f"{value / (1 << 20):.3g} MiB"
    return f"{value:,} {unit}"


def check_limit(name: str, value: int, what: str, hint: str = "") -> None:
    """Raise :class:`ResourceLimitError` when ``value`` exceeds the limit ``name``; ``what`` says what
    would have been allocated, naming the file or argument (``"depth in big.npz (100000x100000)"``),
    ``hint`` what else would help."""
    cap = limit(name)
    if value > cap:
        env, _, unit = LIMITS[name]
        raise ResourceLimitError(f"{what}: needs {_size(value, unit)}, above the limit of {_size(cap, unit)} "
                                 f"({env} raises it{'; ' + hint if hint else ''})")


#: Bytes per pixel of the walk without gradients, per step (one side's steps are fetched together),
#: and with gradients, per slice and step (autograd keeps every sample), plus the G-buffer's own;
#: measured on the tensor-op walk (float32; the fused kernels need less), rounded up.
_BASE, _PER_STEP, _PER_SAMPLE_GRAD = 256, 128, 256


def walk_bytes(batch: int, height: int, width: int, slices: int, steps: int, *, grad: bool,
               chunk_size: int | None = None, recompute: bool = False) -> int:
    """An upper estimate of the memory of one method call (bytes) on ``batch x height x width`` pixels
    at ``slices x steps``: ``pixels * 256`` for the G-buffer and outputs plus, per pixel walked at once
    (a ``chunk_size`` caps it), ``128 * steps`` without gradients and ``256 * slices * steps`` with
    them (all pixels' graphs are kept unless ``recompute`` with a ``chunk_size``)."""
    pixels = batch * height * width
    at_once = pixels if chunk_size is None else min(pixels, chunk_size)
    kept = at_once if (recompute and chunk_size is not None) else pixels
    return pixels * _BASE + at_once * _PER_STEP * steps + (kept * _PER_SAMPLE_GRAD * slices * steps if grad else 0)

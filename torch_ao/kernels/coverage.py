"""What every kernel's ``covers`` checks the same way: a module's option values and the G-buffer's type."""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer

__all__ = ["option_uncovered", "gbuffer_uncovered", "call_uncovered"]


def option_uncovered(values: dict, covered: dict) -> str | None:
    """The first of a module's option ``values`` (name -> value) a kernel does not reproduce, said as the
    reason, or ``None``. ``covered`` maps each option the kernel knows to ``None`` (any value) or the values
    it covers; an option it does not know (e.g. one added to the module later) is not covered."""
    for name, value in values.items():
        if name not in covered:
            return f"option {name!r} (unknown to the kernel)"
        allowed = covered[name]
        # identity, or equality of strings: True must not pass for 1, nor a tensor compare elementwise
        if allowed is not None and not any(value is a or (isinstance(value, str) and value == a) for a in allowed):
            return f"{name}={value!r}"
    return None


def gbuffer_uncovered(gbuffer: GBuffer) -> str | None:
    """Why the kernels cannot read ``gbuffer`` (not float32 on the CPU or CUDA), or ``None``."""
    if gbuffer.depth.device.type not in ("cpu", "cuda") or gbuffer.depth.dtype != torch.float32:
        return f"a {gbuffer.depth.dtype} G-buffer on {gbuffer.depth.device.type} (the kernels are float32 CPU or CUDA)"
    return None


def call_uncovered(module, gbuffer: GBuffer, options: dict, parameters: tuple[str, ...]) -> str | None:
    """What a forward kernel checks of every call, said as the reason, or ``None``: the module's options
    (:func:`option_uncovered` against ``options``), its ``parameters`` (names) scalar tensors, a float32 G-buffer
    on CPU or CUDA."""
    reason = option_uncovered(getattr(module, "values", {}), options)
    if reason is not None:
        return reason
    values = [getattr(module, name) for name in parameters]
    if any(not isinstance(t, torch.Tensor) or t.dim() != 0 for t in values):
        return "a parameter other than a scalar"
    return gbuffer_uncovered(gbuffer)

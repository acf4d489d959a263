"""Counting how often dispatch hands a call to a kernel (``backend="auto"`` tests)."""
import torch_ao.kernels.dispatch as dispatch


def count_kernel_calls(monkeypatch, name: str) -> list:
    """Wrap the last ``(covers, run)`` entry of ``dispatch.KERNELS[name]`` so that each run appends 1 to
    the returned list; the entry's ``covers`` is kept, so coverage decides as before."""
    *others, (covers, run) = dispatch.KERNELS[name]
    calls = []
    monkeypatch.setitem(dispatch.KERNELS, name, (*others, (covers, lambda *a: calls.append(1) or run(*a))))
    return calls

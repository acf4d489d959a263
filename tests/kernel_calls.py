"""Counting how often dispatch hands a call to a kernel (``backend="auto"`` tests); a call on given numbers of
torch's threads."""
import torch

import torch_ao.kernels.dispatch as dispatch


def on_threads(fn, counts=(1, 2)) -> list:
    """``[fn() with torch on n threads for n in counts]``, torch's thread count restored after."""
    threads = torch.get_num_threads()
    results = []
    try:
        for n in counts:
            torch.set_num_threads(n)
            results.append(fn())
    finally:
        torch.set_num_threads(threads)
    return results


def count_kernel_calls(monkeypatch, name: str, covers=None) -> list:
    """Wrap the ``(covers, run)`` entry of ``dispatch.KERNELS[name]`` (the last, or the one of ``covers``) so that
    each run appends 1 to the returned list; the entry's ``covers`` is kept, so coverage decides as before."""
    entries = list(dispatch.KERNELS[name])
    index = len(entries) - 1 if covers is None else [c for c, _ in entries].index(covers)
    wrapped, run = entries[index]
    calls = []
    entries[index] = (wrapped, lambda *a: calls.append(1) or run(*a))
    monkeypatch.setitem(dispatch.KERNELS, name, tuple(entries))
    return calls

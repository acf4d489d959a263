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


def count_kernel_calls(monkeypatch, name: str) -> list:
    """Wrap the last ``(covers, run)`` entry of ``dispatch.KERNELS[name]`` so that each run appends 1 to
    the returned list; the entry's ``covers`` is kept, so coverage decides as before."""
    *others, (covers, run) = dispatch.KERNELS[name]
    calls = []
    monkeypatch.setitem(dispatch.KERNELS, name, (*others, (covers, lambda *a: calls.append(1) or run(*a))))
    return calls

"""Peak memory of one call on the CPU, as the benchmarks measure it: in a process of its own, the peak resident
set size of its address space (``VmHWM``) after the call minus the resident size just before it (after the
imports and the inputs' set-up). A fresh process per case keeps the peak honest: the peak never falls, and a
process that ran other cases before would have their freed pages to reuse. ``VmHWM``, not ``ru_maxrss``:
Linux carries ``ru_maxrss`` over ``execve`` from the address space the child was forked from, so a case
started by a large parent would report the parent's resident size as its own peak.

    from peak_memory import PeakMemory       # a benchmark script's sibling (its folder is on sys.path)

    with PeakMemory() as peak:
        out = module(gbuffer); out.visibility.sum().backward()
    peak.mb                                  # MiB above the resident size at entry
"""
from __future__ import annotations

import os


def resident_kb() -> int:
    """The process's resident set size now, KiB (``/proc/PID/statm``)."""
    with open(f"/proc/{os.getpid()}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def peak_resident_kb() -> int:
    """The peak resident set size of the process's address space so far, KiB (``VmHWM``)."""
    with open(f"/proc/{os.getpid()}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    raise RuntimeError("/proc/PID/status has no VmHWM line")


class PeakMemory:
    """The peak resident set above the resident size at ``start`` (MiB: ``mb``, set by ``stop``; ``baseline_mb``
    that resident size); a context manager too. Meaningful for the first measured span of a process (see the
    module docstring)."""

    def start(self) -> "PeakMemory":
        self.baseline_kb = resident_kb()
        self.mb = float("nan")
        return self

    def stop(self) -> float:
        self.mb = (peak_resident_kb() - self.baseline_kb) / 1024.0
        return self.mb

    def __enter__(self) -> "PeakMemory":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def baseline_mb(self) -> float:
        return self.baseline_kb / 1024.0

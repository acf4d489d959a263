"""Time the soft sector union (:mod:`torch_ao.sectors`) on CPU.

Forward: ``sector_union(..., mode="soft", tau=0.25)`` under ``no_grad``; forward + backward:
``SectorUnion.apply`` then ``backward``, on ``s = rand(N, J) * 28``, ``w = rand(N, J) * 4``, with and
without per-sector weights (the ``newly`` output). Prints the median (and the minimum) of ``--repeat`` runs in ms.

A 30 MB tensor is allocated and freed first (``--cold-allocator`` skips it): glibc then serves the
union's scratch buffers from its heap, as in a real frame where large tensors come and go; in a fresh
process it may instead map (and page-fault) them anew on every call, a cost of the allocator's state
rather than of the union.

    python benchmarks/bench_sectors.py [--rows 16384] [--steps 16] [--threads 1] [--repeat 15] [--cold-allocator]
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from torch_ao.sectors import SectorUnion, sector_union


def _times_ms(fn, repeat: int) -> tuple[float, float]:
    """(median, min) wall time of ``fn`` in ms over ``repeat`` runs, after one warm-up run."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times), 1e3 * min(times)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=16384)
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--tau", type=float, default=0.25)
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--cold-allocator", action="store_true", help="skip the allocator warm-up")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if not args.cold_allocator:
        torch.empty(30 * 2**20 // 4).fill_(0)  # raises glibc's mmap threshold (see the module docstring)
    dtype = getattr(torch, args.dtype)
    g = torch.Generator().manual_seed(0)
    N, J, tau = args.rows, args.steps, args.tau
    s = torch.rand(N, J, generator=g, dtype=dtype) * 28
    w = torch.rand(N, J, generator=g, dtype=dtype) * 4
    weights = torch.rand(N, 32, generator=g, dtype=dtype)
    weights /= weights.sum(-1, keepdim=True)
    print(f"sector union, N={N} J={J} tau={tau} {args.dtype}, {args.threads} thread(s), median of {args.repeat}")
    for label, wt in (("no weights", None), ("weights   ", weights)):
        def fwd():
            with torch.no_grad():
                sector_union(s, w, mode="soft", tau=tau, weights=wt)

        sg, wg = s.clone().requires_grad_(), w.clone().requires_grad_()
        wtg = None if wt is None else wt.clone().requires_grad_()

        def fwd_bwd():
            vis, newly = SectorUnion.apply(sg, wg, wtg, None, tau, "ceil", False)
            loss = vis.sum() if wtg is None else vis.sum() + newly.sum()
            loss.backward()
            sg.grad = wg.grad = None
            if wtg is not None:
                wtg.grad = None

        f, fmin = _times_ms(fwd, args.repeat)
        fb, fbmin = _times_ms(fwd_bwd, args.repeat)
        print(f"{label}: forward {f:7.2f} ms (min {fmin:6.2f})   forward+backward {fb:7.2f} ms (min {fbmin:6.2f})"
              f"   backward ~{fb - f:6.2f} ms")


if __name__ == "__main__":
    main()

"""Fitting over many frames: peak memory with the views in memory against read on access
(:class:`~torch_ao.fit_data.ViewFiles`), and the wall time of one process against ``torchrun`` ranks.

Run: ``python benchmarks/bench_fit_scale.py [--frames 96] [--size 256x144] [--steps 2] [--ranks 2]``.

It writes ``--frames`` G-buffer files (a floor and a wall under varied cameras, reference: GTAO at
another final power) to a temporary folder, then fits GTAO's radius and final power (preset low, every
view each step, hard-mode scores at the start and the end) in fresh processes:

* ``in memory``: :func:`~torch_ao.views.load_views` of every file, then :func:`~torch_ao.fit.fit`, on all
  cores' threads;
* ``streamed``: a :class:`~torch_ao.fit_data.ViewFiles` of the files (cache of 2), on all cores' threads,
  and on one;
* ``streamed, N ranks``: the same under ``torchrun --nproc_per_node N`` (gloo), each rank on
  ``cores / N`` threads.

Per run: the peak resident memory (``ru_maxrss``) above the process's after the imports (the largest
rank's), the fit's wall time, and the fitted parameters (the same in every run, up to the float sums'
order). Compare within one run of this script: the machine may be shared.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _module():
    from torch_ao.methods import get_method

    return get_method("gtao")(preset="low", radius=1.0, falloff_range=0.25)


def write_frames(folder: Path, frames: int, width: int, height: int) -> list[Path]:
    import torch

    from torch_ao.examples import floor_wall_gbuffer
    from torch_ao.io import save_npz

    reference = _module()
    with torch.no_grad():
        reference.final_power.fill_(1.4)
    paths = []
    for i in range(frames):
        gb, _ = floor_wall_gbuffer(height, width, wall_distance=0.8 + 0.01 * i, camera_height=2.5 + 0.02 * i,
                                   pitch_degrees=-50 - 0.2 * i)
        with torch.no_grad():
            ao = reference(gb).visibility
        paths.append(save_npz(folder / f"frame{i:04d}.npz", gb, ao=ao, max_distance=torch.tensor(1.0)))
    return paths


def child(folder: str, mode: str, steps: int) -> None:
    """One measured fit (this process, or one rank under torchrun); prints a JSON line per rank."""
    import torch

    from torch_ao import distributed
    from torch_ao.fit import FitConfig, fit, load_views
    from torch_ao.fit_data import ViewFiles

    distributed.init_from_environment("cpu")
    base = _rss_mb()
    paths = sorted(Path(folder).glob("*.npz"))
    t0 = time.perf_counter()
    views = load_views(paths) if mode == "memory" else ViewFiles(paths, cache_size=2)
    module = _module()
    cfg = FitConfig(params=("radius", "final_power"), steps=steps, lr=0.02, hard_every=steps)
    result = fit(module, views, cfg, progress=False)
    print(json.dumps({"rank": distributed.rank(), "seconds": time.perf_counter() - t0, "rss_mb": _rss_mb() - base,
                      "parameters": result.parameters}), flush=True)
    if distributed.is_distributed():
        torch.distributed.destroy_process_group()


def _run(cmd: list[str], threads: int) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "OMP_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode:
        raise SystemExit(proc.stdout[-3000:] + proc.stderr[-3000:])
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=96)
    p.add_argument("--size", default="256x144")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--ranks", type=int, default=2)
    p.add_argument("--child", nargs=2, metavar=("FOLDER", "MODE"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(*args.child, args.steps)
        return 0
    width, height = (int(x) for x in args.size.split("x"))
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        write_frames(Path(tmp), args.frames, width, height)
        me = [sys.executable, __file__, "--steps", str(args.steps), "--child", tmp]
        runs = {f"in memory, {cores} threads": _run([*me, "memory"], cores),
                f"streamed, {cores} threads": _run([*me, "streamed"], cores),
                "streamed, 1 thread": _run([*me, "streamed"], 1),
                f"streamed, {args.ranks} ranks x {max(1, cores // args.ranks)} threads": _run(
                    [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.ranks}",
                     *me[1:], "streamed"], max(1, cores // args.ranks))}
    print(f"{args.frames} frames at {width}x{height}, GTAO low, {args.steps} steps; {cores} cores, "
          f"load average {os.getloadavg()[0]:.1f}")
    print("| run | peak memory above imports (MB) | fit wall (s) | radius | final_power |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, ranks in runs.items():
        r = ranks[0]
        print(f"| {name} | {max(x['rss_mb'] for x in ranks):.0f} | {max(x['seconds'] for x in ranks):.2f} | "
              f"{r['parameters']['radius']:.6f} | {r['parameters']['final_power']:.6f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

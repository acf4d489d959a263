"""Run time of the main job, ``torch-ao fit`` with its defaults, from an empty reference cache, by phase.

Run: ``python benchmarks/bench_fit.py [--repeat N] [--cold-kernels] [-- extra torch-ao fit flags]``.

Each run is a fresh process (imports and kernel loading are part of the job) with ``$TORCH_AO_CACHE``
pointing at an empty folder, so every reference is ray-traced. Inside it, the phases are timed by
wrapping the functions that do them (time inside a nested phase counts for that phase only):

* ``imports``: from the process start until ``torch_ao.cli`` and the fit command are imported;
* ``kernel load``: ``torch_ao.kernels.build.load_cached_library`` (building the C++ libraries when the
  build cache ``$TORCH_EXTENSIONS_DIR`` does not hold them: ``--cold-kernels`` gives it an empty one);
* ``render``: ``render_reference`` (the references of the 18 views);
* ``fit loop``: ``torch_ao.fit.fit`` (soft steps and the hard-mode checks of the training views);
* ``scoring``: ``evaluate`` of the held-out tables (7 pipelines);
* ``other``: the rest (loading the cached files, writing the outputs, the PNG).

Wall and CPU (``time.process_time``: user + sys of all threads) per phase, and the child's whole wall
time and CPU time (``wait4``). The machine's load is printed: on a shared machine compare CPU times.
"""
from __future__ import annotations

import json
import time

_T0_WALL, _T0_CPU = time.perf_counter(), time.process_time()

import argparse  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

PHASES = ("imports", "kernel load", "render", "fit loop", "scoring", "other")


class _Phases:
    """Exclusive wall and CPU time per phase: a phase entered inside another pauses the outer one."""

    def __init__(self):
        self.wall = dict.fromkeys(PHASES, 0.0)
        self.cpu = dict.fromkeys(PHASES, 0.0)
        self.calls = dict.fromkeys(PHASES, 0)
        self.stack = ["other"]
        self.mark = (time.perf_counter(), time.process_time())

    def _switch(self, to: str | None) -> None:
        now = (time.perf_counter(), time.process_time())
        top = self.stack[-1]
        self.wall[top] += now[0] - self.mark[0]
        self.cpu[top] += now[1] - self.mark[1]
        self.mark = now
        if to is None:
            self.stack.pop()
        else:
            self.stack.append(to)
            self.calls[to] += 1

    def wrap(self, phase: str, fn):
        def timed(*args, **kwargs):
            self._switch(phase)
            try:
                return fn(*args, **kwargs)
            finally:
                self._switch(None)

        return timed


def child(fit_args: list[str]) -> None:
    import torch_ao.cli as cli
    import torch_ao.commands.fit as fit_cmd
    import torch_ao.kernels.build as build
    import torch_ao.reference as reference

    phases = _Phases()
    phases.wall["imports"] = time.perf_counter() - _T0_WALL
    phases.cpu["imports"] = time.process_time() - _T0_CPU
    from torch.utils import cpp_extension

    cpp_extension.load = phases.wrap("kernel load", cpp_extension.load)
    if hasattr(build, "load_cached_library"):  # (absent before the build cache: then cpp_extension.load alone)
        build.load_cached_library = phases.wrap("kernel load", build.load_cached_library)
    reference.render_reference = phases.wrap("render", reference.render_reference)
    fit_cmd.fit = phases.wrap("fit loop", fit_cmd.fit)
    fit_cmd.evaluate = phases.wrap("scoring", fit_cmd.evaluate)
    status = cli.main(["fit", *fit_args])
    phases._switch(None)
    print("BENCH_FIT " + json.dumps({"wall": phases.wall, "cpu": phases.cpu, "calls": phases.calls,
                                     "status": status}), flush=True)


def run_once(fit_args: list[str], cold_kernels: bool, show_output: bool) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_fit_") as tmp:
        env = dict(os.environ, TORCH_AO_CACHE=str(Path(tmp) / "cache"),
                   PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]))
        if cold_kernels:
            env["TORCH_EXTENSIONS_DIR"] = str(Path(tmp) / "torch_extensions")
        argv = [sys.executable, __file__, "--child", "--", "--no-progress", "--out", str(Path(tmp) / "out"), *fit_args]
        t = time.perf_counter()
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, text=True)
        out = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
    lines = out.splitlines()
    found = [json.loads(line[len("BENCH_FIT "):]) for line in lines if line.startswith("BENCH_FIT ")]
    if os.waitstatus_to_exitcode(status) != 0 or not found:
        sys.stdout.write(out)
        raise SystemExit(f"torch-ao fit failed (exit status {os.waitstatus_to_exitcode(status)})")
    if show_output:
        print("\n".join(line for line in lines if not line.startswith("BENCH_FIT ")))
    result = found[0]
    result["total_wall"] = wall
    result["total_cpu"] = usage.ru_utime + usage.ru_stime
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=1, help="runs (each from an empty cache)")
    ap.add_argument("--cold-kernels", action="store_true", help="an empty C++ build cache too (includes the builds)")
    ap.add_argument("--show-output", action="store_true", help="print the fit's own output (its tables)")
    ap.add_argument("fit_args", nargs="*", help="extra flags of torch-ao fit (after --)")
    args = ap.parse_args()
    if args.child:
        child(args.fit_args)
        return
    import torch

    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, load average before {os.getloadavg()[0]:.1f}")
    print("| run | " + " | ".join(f"{p} wall / CPU s" for p in PHASES) + " | total wall s | total CPU s | load |")
    print("|---" * (len(PHASES) + 4) + "|")
    for i in range(args.repeat):
        r = run_once(args.fit_args, args.cold_kernels, args.show_output)
        cells = [f"{r['wall'][p]:.1f} / {r['cpu'][p]:.1f}" for p in PHASES]
        print(f"| {i + 1} | " + " | ".join(cells) + f" | {r['total_wall']:.1f} | {r['total_cpu']:.1f} | "
              f"{os.getloadavg()[0]:.1f} |", flush=True)


if __name__ == "__main__":
    main()

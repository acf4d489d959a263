"""The error-against-run-time report and the background study, as run for the README.

    python benchmarks/bench_error_vs_time.py --quick --threads 1 --out bench_quick     # the 2-core CPU run
    python benchmarks/bench_error_vs_time.py --out bench_full --device cuda            # a GPU run

runs ``torch-ao bench`` with the given flags, then times every available method on a full frame, the
same frame with half its pixels background, and an all-background frame at a few sizes, and writes
``background.md`` next to the bench report. Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from torch_ao.bench import available_methods, background_scaling
from torch_ao.cli import main as cli_main
from torch_ao.examples import plane_gbuffer


def background_table(rows: list[dict]) -> str:
    lines = ["| method | size | frame | walked pixels | forward ms | time / full | CPU ms | CPU / full |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['method']} {r['preset']} | {r['width']}x{r['height']} | {r['frame']} | {r['walked_pixels']} | "
                     f"{r['forward_ms']:.1f} | {r['time_ratio']:.2f} | {r['forward_cpu_ms']:.1f} | {r['cpu_ratio']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench", help="output folder (the bench report and background.md)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int)
    parser.add_argument("--sizes", default="128x96,256x192", help="background study frame sizes WxH, comma-separated")
    parser.add_argument("--preset", default="high", help="preset of the background study")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-bench", action="store_true", help="only the background study")
    args, bench_args = parser.parse_known_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if not args.skip_bench:
        extra = ["--threads", str(args.threads)] if args.threads else []
        rc = cli_main(["bench", "--out", args.out, "--device", args.device, *extra, *bench_args])
        if rc:
            return rc
    methods = available_methods()
    rows = []
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.lower().split("x"))
        rows += background_scaling(methods, args.preset, gbuffer=plane_gbuffer(h, w), repeats=args.repeats,
                                   device=args.device, progress=True)
    text = ("# Background costs nothing\n\nA tilted plane filling the frame (`full`), the same frame with its right half "
            "background (`half`) and all background (`empty`); medians of "
            f"{args.repeats} runs, {torch.get_num_threads()} torch threads, device {args.device}.\n\n"
            + background_table(rows) + "\n")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "background.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

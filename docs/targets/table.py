"""The per-scene PSNR table of docs/accuracy.md's "Targets (issue 13)" from the fits' params.json files:
each fitted pipeline's held-out PSNR, GTAO fitted and at its defaults, and the differences.

    python docs/targets/table.py docs/targets/{bitmask,exact,backface,linear}/params.json --gtao docs/targets/gtao/params.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("params", nargs="+")
    p.add_argument("--gtao", required=True)
    args = p.parse_args()
    gtao = json.loads(Path(args.gtao).read_text())["per_view"]
    fits = {Path(f).parent.name: json.loads(Path(f).read_text())["per_view"]["fitted"] for f in args.params}
    views = list(gtao["fitted"])
    head = ["scene", *(f"{n} fitted" for n in fits), "GTAO fitted", "GTAO default",
            *(f"{n} − GTAO fitted" for n in fits), *(f"{n} − GTAO default" for n in fits)]
    print("| " + " | ".join(head) + " |")
    print("| --- |" + " ---: |" * (len(head) - 1))
    rows = {v: [f[v]["psnr"] for f in fits.values()] for v in views}
    for v in views:
        g, d = gtao["fitted"][v]["psnr"], gtao["default"][v]["psnr"]
        cells = [f"{x:.2f}" for x in rows[v]] + [f"{g:.2f}", f"{d:.2f}"]
        cells += [f"{x - g:+.2f}" for x in rows[v]] + [f"{x - d:+.2f}" for x in rows[v]]
        print(f"| {v.split('/')[0]} | " + " | ".join(cells) + " |")
    mean = lambda xs: sum(xs) / len(xs)
    m = [mean([rows[v][i] for v in views]) for i in range(len(fits))]
    g, d = mean([gtao["fitted"][v]["psnr"] for v in views]), mean([gtao["default"][v]["psnr"] for v in views])
    cells = [f"{x:.2f}" for x in m] + [f"{g:.2f}", f"{d:.2f}"] + [f"{x - g:+.2f}" for x in m] + [f"{x - d:+.2f}" for x in m]
    print("| **mean** | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()

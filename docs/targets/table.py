"""The per-scene PSNR tables of docs/accuracy.md's "Fitted pipelines against the strongest GTAO" from the fits' params.json files.

Each scene's PSNR is the mean over its held-out views (``<scene>/s1000``, ``s1001``...). The first table has
every fitted pipeline, every GTAO fit and GTAO's defaults; the second each bitmask pipeline against the
*strongest* GTAO fit of each scene (the best of the GTAO fits given: "GTAO tuned with the same tooling"), with the
targets' verdict.

    python docs/targets/table.py docs/targets/{backface_edge,exact_backface_edge}/params.json \\
        --gtao docs/targets/{gtao,gtao_edge}/params.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

#: issue 13's targets: mean PSNR, the margin on thin-occluder scenes, the largest shortfall anywhere (dB)
MEAN_TARGET, THIN_SCENES, THIN_MARGIN, MAX_SHORTFALL = 28.0, ("fence", "poles"), 3.0, 0.5


def per_scene(views: dict) -> dict[str, float]:
    """``{scene: mean PSNR over its views}`` in the views' order."""
    scenes: dict[str, list[float]] = {}
    for name, metrics in views.items():
        scenes.setdefault(name.split("/")[0], []).append(metrics["psnr"])
    return {s: sum(v) / len(v) for s, v in scenes.items()}


def report(fits: dict[str, dict], gtao: dict[str, dict], gtao_default: dict) -> None:
    """Print the tables and the verdict: ``fits`` and ``gtao`` map a column name to its per-view metrics
    (``{"<scene>/s<seed>": {"psnr": ...}}``), ``gtao_default`` is GTAO's at its defaults."""
    fits = {n: per_scene(v) for n, v in fits.items()}
    gtao = {n: per_scene(v) for n, v in gtao.items()}
    scenes = list(next(iter(gtao.values())))
    mean = lambda xs: sum(xs) / len(xs)

    columns = {**fits, **gtao, "GTAO default": per_scene(gtao_default)}
    print("| scene | " + " | ".join(columns) + " |")
    print("| --- |" + " ---: |" * len(columns))
    for s in scenes:
        print(f"| {s} | " + " | ".join(f"{c[s]:.2f}" for c in columns.values()) + " |")
    print("| **mean** | " + " | ".join(f"{mean(list(c.values())):.2f}" for c in columns.values()) + " |")

    best = {s: max(g[s] for g in gtao.values()) for s in scenes}
    which = {s: max(gtao, key=lambda g: gtao[g][s]) for s in scenes}
    print("\n| scene | strongest GTAO | PSNR | " + " | ".join(f"{n} − it" for n in fits) + " |")
    print("| --- | --- | ---: |" + " ---: |" * len(fits))
    for s in scenes:
        print(f"| {s} | {which[s]} | {best[s]:.2f} | " + " | ".join(f"{f[s] - best[s]:+.2f}" for f in fits.values()) + " |")
    print()
    for n, f in fits.items():
        thin = min(f[s] - best[s] for s in THIN_SCENES if s in f)
        worst = min(scenes, key=lambda s: f[s] - best[s])
        print(f"{n}: mean {mean(list(f.values())):.2f} dB (>= {MEAN_TARGET:g}: {mean(list(f.values())) >= MEAN_TARGET}); "
              f"thin occluders {thin:+.2f} (>= +{THIN_MARGIN:g}: {thin >= THIN_MARGIN}); "
              f"worst {worst} {f[worst] - best[worst]:+.2f} (>= -{MAX_SHORTFALL:g}: {f[worst] - best[worst] >= -MAX_SHORTFALL})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("params", nargs="+", help="the bitmask fits' params.json")
    p.add_argument("--gtao", nargs="+", required=True, help="the GTAO fits' params.json (their defaults are added)")
    args = p.parse_args()
    load = lambda f: json.loads(Path(f).read_text())["per_view"]
    report({Path(f).parent.name: load(f)["fitted"] for f in args.params},
           {f"GTAO {Path(f).parent.name}": load(f)["fitted"] for f in args.gtao}, load(args.gtao[0])["default"])


if __name__ == "__main__":
    main()

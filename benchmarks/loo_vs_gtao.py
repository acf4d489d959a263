"""The shipped pipeline against the best GTAO a user could have, scene by scene, on scenes no fit saw.

Runs ``torch-ao fit --leave-one-out`` three times (each resumable in its own ``--out`` folder): the default
pipeline, GTAO with the bilinear fetch and GTAO with the edge-aware fetch. For each scene of the fit set it then
compares the default pipeline fitted on the other scenes with the best of four GTAOs on that scene (each fetch at
its defaults, and fitted on the other scenes); for the held-out scenes, which no fit trains on, with the main fits'
held-out views. Last, the forward time of the fitted pipeline against GTAO ``high`` + denoiser on every view
(interleaved, one thread: the median over views of each view's fastest of 5 runs). Prints the four numbers
of docs/accuracy.md's report, the per-scene table as Markdown:

    OMP_NUM_THREADS=1 python benchmarks/loo_vs_gtao.py --out loo-runs      # about 10 minutes on one thread
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from pipeline_candidates import fit_view_groups
from torch_ao.cli import main as cli
from torch_ao.fitted import FittedPipeline, load_fitted

#: the default pipeline; GTAO at ``high`` (its best split of the cost: docs/fitting.md) with either fetch
RUNS = {"shipped": [], "gtao": ["--method", "gtao", "--fetch", "bilinear", "--preset", "high"],
        "gtao edge_aware": ["--method", "gtao", "--fetch", "edge_aware", "--preset", "high"]}


def run(out: str, extra: list[str]) -> dict:
    """One ``torch-ao fit --leave-one-out`` (resumed when ``out`` holds it) and its params.json."""
    if cli(["fit", "--leave-one-out", "--no-progress", "--out", out, *extra]) != 0:
        raise SystemExit(f"torch-ao fit {' '.join(extra)} failed")
    with open(os.path.join(out, "params.json")) as f:
        return json.load(f)


def per_scene(data: dict) -> dict[str, dict[str, dict[str, float]]]:
    """PSNR per scene ``{group: {"fitted" | "default": {scene: dB}}}``: group ``"left out"`` (fit-set scenes,
    fitted on the others) and ``"held-out scene"`` (fitted on the fit set by the main fit)."""
    loo = data["leave_one_out"]
    held = {which: {name.split("/")[0]: m["psnr"] for name, m in data["per_view"][which].items()
                    if name.split("/")[0] not in loo} for which in ("fitted", "default")}
    return {"left out": {which: {s: r[which] for s, r in loo.items()} for which in ("fitted", "default")},
            "held-out scene": held}


def time_ratio(pipeline, repeats: int = 5) -> tuple[float, float]:
    """Median per-view forward seconds of ``pipeline`` and of GTAO ``high`` + denoiser, run interleaved."""
    gtao = FittedPipeline("gtao", {"preset": "high", "radius": 1.0}, denoiser=True)
    views = [v for group in fit_view_groups().values() for v in group]
    best = {"pipeline": [float("inf")] * len(views), "gtao": [float("inf")] * len(views)}
    with torch.no_grad():
        for _ in range(repeats):
            for i, view in enumerate(views):
                for key, module in (("pipeline", pipeline), ("gtao", gtao)):
                    start = time.perf_counter()
                    module(view.gbuffer)
                    best[key][i] = min(best[key][i], time.perf_counter() - start)
    return statistics.median(best["pipeline"]), statistics.median(best["gtao"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="loo-runs", help="folder of the three runs (resumed when present)")
    args = p.parse_args()
    data = {label: run(os.path.join(args.out, label.replace(" ", "_")), extra) for label, extra in RUNS.items()}
    results = {label: per_scene(d) for label, d in data.items()}
    shipped = results["shipped"]
    rows, margins = [], []
    for group, ours in shipped.items():
        for scene, psnr in ours["fitted"].items():
            candidates = {f"{label} {which}": results[label][group][which][scene]
                          for label in ("gtao", "gtao edge_aware") for which in ("fitted", "default")}
            best = max(candidates, key=candidates.get)
            margins.append(psnr - candidates[best])
            rows.append(f"| {scene} ({group}) | {psnr:.2f} | {candidates[best]:.2f} ({best}) | {margins[-1]:+.2f} |")
    print("| scene | shipped, fitted without it | best GTAO | difference |")
    print("| --- | ---: | ---: | ---: |")
    print("\n".join(rows))
    folds = list(shipped["left out"]["fitted"].values())
    print(f"\nleave-one-out mean {statistics.mean(folds):.2f} dB over {len(folds)} scenes; the one fit over all of "
          f"them on the {len(data['shipped']['holdout_views'])} held-out views {data['shipped']['after']['psnr']:.2f} dB; "
          f"worst scene against the best GTAO {min(margins):+.2f} dB")
    torch.set_num_threads(1)
    ours, gtao = time_ratio(load_fitted(os.path.join(args.out, "shipped", "params.json")))
    print(f"forward time {1000 * ours:.2f} ms against GTAO high + denoiser {1000 * gtao:.2f} ms: {ours / gtao:.2f}x")


if __name__ == "__main__":
    main()

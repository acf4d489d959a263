"""Which pipeline should ``torch-ao fit`` fit by default? Every candidate (method, variant, thickness model,
fetch, with the denoiser) in hard mode on the views ``torch-ao fit`` uses: the fit scenes' training views, their
held-out views, and the held-out scenes' views, reported separately; at its default parameters, or (``--fitted``)
as ``torch-ao fit`` with the candidate's flags fits it on the training views (the choice is by the training
views' column: fitting moves some candidates much more than others).

    python benchmarks/pipeline_candidates.py                  # 160x96, 256 spp: torch-ao fit's views
    python benchmarks/pipeline_candidates.py --fitted         # each fitted by torch-ao fit (a few minutes each)
    python benchmarks/pipeline_candidates.py --size 96x72 --spp 64 --train-views 1
    python benchmarks/pipeline_candidates.py --fitted --only default     # the rows whose label has "default"

Prints a Markdown table: mean PSNR (dB) per view group and the median forward time per view (ms).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import tempfile

import torch

from torch_ao.cli import main as cli
from torch_ao.datasets import HOLDOUT_SEED, parse_scenes, reference_views, train_and_holdout_views
from torch_ao.fit import evaluate
from torch_ao.fitted import FittedPipeline, load_fitted
from torch_ao.methods import DEFAULT_PRESET

#: (label, method, options): the pipeline `torch-ao fit` fits with no flags first
CANDIDATES = (
    ("bitmask cosine backface edge_aware very_high_steps staggered screen (the default)", "bitmask",
     {"weighting": "cosine", "thickness_model": "backface", "fetch": "edge_aware", "preset": "very_high_steps",
      "stagger": True, "azimuth": "screen"}),
    ("bitmask cosine backface edge_aware very_high", "bitmask",
     {"weighting": "cosine", "thickness_model": "backface", "fetch": "edge_aware", "preset": "very_high"}),
    ("bitmask cosine backface edge_aware high_steps", "bitmask",
     {"weighting": "cosine", "thickness_model": "backface", "fetch": "edge_aware", "preset": "high_steps"}),
    ("bitmask cosine backface edge_aware", "bitmask",
     {"weighting": "cosine", "thickness_model": "backface", "fetch": "edge_aware"}),
    ("bitmask cosine edge_aware high_steps", "bitmask", {"weighting": "cosine", "fetch": "edge_aware", "preset": "high_steps"}),
    ("bitmask cosine", "bitmask", {"weighting": "cosine"}),
    ("bitmask cosine edge_aware", "bitmask", {"weighting": "cosine", "fetch": "edge_aware"}),
    ("bitmask cosine backface", "bitmask", {"weighting": "cosine", "thickness_model": "backface"}),
    ("bitmask exact", "bitmask", {"variant": "exact"}),
    ("bitmask exact backface edge_aware", "bitmask",
     {"variant": "exact", "thickness_model": "backface", "fetch": "edge_aware"}),
    ("gtao", "gtao", {}),
    ("gtao edge_aware", "gtao", {"fetch": "edge_aware"}),
    ("gtao high_steps", "gtao", {"preset": "high_steps"}),
    ("gtao very_high", "gtao", {"preset": "very_high"}),
)


def fit_view_groups(size: str = "160x96", spp: int = 256, train_views: int = 2) -> dict:
    """``torch-ao fit``'s views at ``size`` (``"WxH"``), in three groups ``{label: [FitView]}``: the fit scenes'
    ``train_views`` training views, their held-out views, and the held-out scenes' views (R = 1, back-face
    layers, ``spp`` rays per pixel)."""
    w, h = (int(x) for x in size.split("x"))
    common = dict(height=h, width=w, spp=spp, max_distance=1.0, backface=True, device=torch.device("cpu"))
    train, held = train_and_holdout_views(parse_scenes("fit"), train_views, 1, **common)
    other = reference_views(parse_scenes("heldout"), [HOLDOUT_SEED], **common)
    return {"fit scenes, training views": train, "fit scenes, held-out views": held, "held-out scenes": other}


def fit_flags(method: str, options: dict) -> list[str]:
    """The ``torch-ao fit`` flags that fit the candidate ``method`` with ``options`` (every choice spelled out,
    so that no default of the command's decides)."""
    flags = ["--method", method, "--fetch", options.get("fetch", "bilinear"), "--azimuth", options.get("azimuth", "view"),
             "--stagger" if options.get("stagger") else "--no-stagger"]
    if method == "bitmask":
        flags += ["--thickness", options.get("thickness_model", "scalar"), "--weighting", options.get("weighting", "cosine")]
    if "variant" in options:
        flags += ["--variant", options["variant"]]
    return flags


def fitted_pipeline(method: str, options: dict, args, folder: str) -> FittedPipeline:
    """The candidate as ``torch-ao fit`` fits it on the training views of ``args``' size (its params.json,
    written under ``folder``)."""
    out = os.path.join(folder, f"{method}-{len(os.listdir(folder))}")
    flags = ["fit", *fit_flags(method, options), "--preset", options.get("preset", args.preset), "--size", args.size,
             "--spp", str(args.spp), "--train-views", str(args.train_views), "--no-progress", "--out", out]
    with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
        if cli(flags) != 0:
            raise SystemExit(f"torch-ao {' '.join(flags)} failed")
    return load_fitted(os.path.join(out, "params.json"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="160x96")
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--train-views", type=int, default=2)
    p.add_argument("--preset", default=DEFAULT_PRESET, help="preset of every candidate but those that name theirs")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--fitted", action="store_true", help="score each candidate as torch-ao fit fits it")
    p.add_argument("--only", nargs="+", help="the candidates whose label contains one of these (default: all)")
    args = p.parse_args()
    groups = fit_view_groups(args.size, args.spp, args.train_views)
    state = "fitted by `torch-ao fit`" if args.fitted else "defaults"
    print(f"| pipeline (+ denoiser, `{args.preset}` unless named, {state}) | " + " | ".join(groups) + " | ms |")
    print("| --- |" + " ---: |" * (len(groups) + 1))
    with tempfile.TemporaryDirectory() as folder:
        for label, method, options in CANDIDATES:
            if args.only and not any(part in label for part in args.only):
                continue
            if args.fitted:
                pipe = fitted_pipeline(method, options, args, folder)
            else:
                pipe = FittedPipeline(method, {"preset": args.preset, "radius": 1.0, **options}, denoiser=True)  # (its own preset wins)
            with torch.no_grad():
                scores = {g: evaluate(pipe, views, repeats=args.repeats) for g, views in groups.items()}
            ms = 1000 * sorted(s["seconds"] for s in scores.values())[1]
            print(f"| {label} | " + " | ".join(f"{s['psnr']:.2f}" for s in scores.values()) + f" | {ms:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()

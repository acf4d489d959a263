"""Fit one scalar bitmask-AO thickness for a set of scenes against ray-traced references.

What it does
    Renders (once, then loads from the cache) randomised views of the built-in scenes with their
    ray-traced reference AO (cosine-weighted, maximum distance ``R``), fits the single ``thickness``
    parameter of :class:`torch_ao.methods.bitmask.BitmaskAO` by gradient descent on the *soft*
    bitmask (:func:`torch_ao.fit.fit`) through the denoiser that follows it in an engine (a
    :class:`torch_ao.fitted.FittedPipeline`), keeps the value that is best in *hard* mode -- the
    integer bitmask an engine ships -- and evaluates it on held-out views (seeds never used for
    fitting). It prints the held-out error of the start value, of common engine defaults (0.25,
    0.5, 1.0) and of the fitted thickness, and writes them to ``OUT/thickness.json``; the fitted
    pipeline goes to ``OUT/params.json`` (``torch-ao ao FRAME --fitted OUT/params.json`` applies it).

How to run
    python training_examples/fit_thickness.py                    # about 5 minutes of CPU time on 2 cores
    python training_examples/fit_thickness.py --steps 100 --size 160x96 --spp 256
    Re-running the same command resumes an interrupted fit from ``OUT/checkpoint.pt``
    (delete the folder, or pass another ``--out``, to start over).

How to adapt
    * Your own G-buffers with references (``torch-ao render``, or ``torch_ao.save_npz`` with an
      ``ao`` array): ``--reference a.npz b.npz --holdout c.npz``.
    * The quality you ship: ``--preset`` (``low``..``ultra``) and ``--weighting uniform`` (the
      paper's equal sectors; ``cosine`` matches the cosine-weighted reference).
    * Another scene mix: ``--scenes fence,poles`` (see ``torch-ao render --list``).
    * More parameters fitted jointly: ``--params thickness,radius``; no denoiser: ``--no-denoise``.
    * In code, this is all there is to it::

          pipeline = FittedPipeline("bitmask", {"preset": "high", "radius": R, "thickness": 1.0}, denoiser=True)
          fit(pipeline, train_views, FitConfig(params=("thickness",), steps=40))
          evaluate(pipeline, held_out_views)    # hard mode
          pipeline.save("params.json")          # torch_ao.load_fitted("params.json") rebuilds it
"""
from __future__ import annotations

import argparse
from pathlib import Path

from torch_ao.datasets import TRAIN_SCENES
from torch_ao.fit import FitConfig, evaluate, fit
from torch_ao.io import save_json

from common import add_bitmask_fit_options, add_run_options, add_view_options, apply_tiny, bitmask, build_views

ENGINE_DEFAULTS = (0.25, 0.5, 1.0)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--reference", nargs="+", metavar="FILE.npz", help="your own training G-buffers with an 'ao' reference")
    p.add_argument("--holdout", nargs="+", metavar="FILE.npz", help="your own held-out references")
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes")
    p.add_argument("--train-views", type=int, default=2, help="randomised training views per scene")
    add_view_options(p, size="96x64")
    add_bitmask_fit_options(p, init_help="initial thickness", steps_help="optimizer steps")
    p.add_argument("--params", default="thickness", help="parameters fitted jointly (thickness, radius)")
    add_run_options(p, out="runs/fit_thickness")
    p.add_argument("--tiny", action="store_true", help="smoke-test settings (options left at their defaults are replaced): 2 scenes, 32x24, 16 spp, 6 steps from thickness 0.2")
    return apply_tiny(p, p.parse_args(argv), scenes="fence,room_corner", train_views=1, size="32x24", spp=16, steps=6, preset="low",
                      init=0.2, hard_every=2)


def main(argv=None) -> dict:
    args = parse_args(argv)
    train, held = build_views(args)
    params = tuple(p.strip() for p in args.params.split(",") if p.strip())
    print(f"bitmask ({args.preset}, {args.weighting}{'' if args.no_denoise else ', + denoiser'}): fitting "
          f"{', '.join(params)} on {len(train)} views, "
          f"evaluating on {len(held)} held-out views, R = {args.max_distance:g}")

    rows = {f"start ({args.init:g})": evaluate(bitmask(args, args.init), held)}
    train_before = evaluate(bitmask(args, args.init), train)
    for t in ENGINE_DEFAULTS:
        rows[f"engine default {t:g}"] = evaluate(bitmask(args, t), held)

    module = bitmask(args, args.init)
    out = Path(args.out)
    cfg = FitConfig(params=params, steps=args.steps, lr=args.lr, batch_views=args.batch_views, seed=args.seed,
                    hard_every=args.hard_every)
    result = fit(module, train, cfg, checkpoint=out / "checkpoint.pt", progress=not args.no_progress)
    thickness = float(module.method.thickness.detach())
    rows[f"fitted ({thickness:.3f})"] = after = evaluate(module, held)
    train_after = evaluate(module, train)

    print(f"\nfitted thickness: {thickness:.4f} (from {args.init:g}, {result.steps_done} steps, {result.seconds:.0f} s; "
          f"radius {float(module.method.radius.detach()):.4f})")
    print(f"\n{'held-out views, hard mode':<26}{'MAE':>8}{'RMSE':>8}{'PSNR':>8}{'SSIM':>8}{'ms':>8}")
    for name, r in rows.items():
        print(f"{name:<26}{r['mae']:8.4f}{r['rmse']:8.4f}{r['psnr']:8.2f}{r['ssim']:8.4f}{r['seconds'] * 1e3:8.1f}")

    module.save(out / "params.json", holdout_after=after)
    payload = {"thickness": thickness, "init": args.init, "preset": args.preset, "weighting": args.weighting,
               "radius_fitted": float(module.method.radius.detach()), "params": list(params),
               "denoiser": not args.no_denoise, "best_step": result.best_step,
               "radius": args.max_distance, "steps": result.steps_done, "fit_seconds": result.seconds,
               "train_views": [v.name for v in train], "holdout_views": [v.name for v in held],
               "holdout": rows, "holdout_before": rows[f"start ({args.init:g})"], "holdout_after": after,
               "train_before": train_before, "train_after": train_after, "history": result.history}
    save_json(out / "thickness.json", payload)
    print(f"\nwrote {out / 'thickness.json'}, {out / 'params.json'}")
    return payload


if __name__ == "__main__":
    main()

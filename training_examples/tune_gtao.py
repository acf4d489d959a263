"""Tune GTAO's (or HBAO's) heuristics against ray-traced references by gradient descent.

What it does
    Renders (once, then loads from the cache) randomised views of the built-in scenes with their
    ray-traced reference AO (cosine-weighted, maximum distance ``R``), then fits the horizon method's
    heuristic parameters with :func:`torch_ao.fit.fit` -- the same loop that fits bitmask thickness,
    through the denoiser that follows the method in an engine (a :class:`torch_ao.fitted.FittedPipeline`;
    ``--no-denoise`` fits the method alone):

    * ``--variant exact`` (default): radius (reported as a multiplier of ``R``), falloff range (a
      fraction of the radius, XeGTAO's ``FalloffRange``) and the final power (``FinalValuePower``);
    * ``--variant ue4``: radius, UE4's thickness heuristic and the final power;
    * ``--variant hdrp``: radius and the final power;
    * ``--method hbao``: every float parameter HBAO exposes (see ``--params``).

    It then prints, on held-out views (seeds never used for fitting, evaluated in hard mode), the
    error of the default parameters, of the values XeGTAO's grid auto-tune reported (radius x1.457,
    falloff 0.615, final power 2.2) and of the fitted values, and writes them to ``OUT/gtao.json``;
    the fitted pipeline goes to ``OUT/params.json`` (``torch-ao ao FRAME --fitted OUT/params.json``).
    XeGTAO tuned against its own ray-traced reference in its own units, so its numbers are a point
    of comparison, not a target.

How to run
    python training_examples/tune_gtao.py                       # about 5 minutes of CPU time on 2 cores
    python training_examples/tune_gtao.py --variant ue4 --steps 80
    python training_examples/tune_gtao.py --method hbao
    Re-running the same command resumes an interrupted fit from ``OUT/checkpoint.pt``.

How to adapt
    * Your own G-buffers with references: ``--reference a.npz b.npz ... --holdout c.npz``
      (files written by ``torch-ao render`` or ``torch_ao.save_npz`` with an ``ao`` array).
    * Another quality: ``--preset ultra`` (or ``--slices/--steps-per-side``); fit at the quality you ship.
    * Other parameters: ``--params radius,final_power``; initial values: ``--init radius=1.2,falloff_range=0.3``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torch_ao.datasets import TRAIN_SCENES
from torch_ao.fit import FitConfig, evaluate, fit, fittable_parameters
from torch_ao.fitted import FittedPipeline
from torch_ao.io import save_json

from common import add_run_options, add_view_options, apply_tiny, build_views

#: XeGTAO's auto-tuned defaults (XeGTAO.h: XE_GTAO_DEFAULT_RADIUS_MULTIPLIER, _FALLOFF_RANGE, _FINAL_VALUE_POWER).
XEGTAO = {"radius_multiplier": 1.457, "falloff_range": 0.615, "final_power": 2.2}
#: Parameters fitted by default, per method/variant.
DEFAULT_PARAMS = {("gtao", "exact"): "radius,falloff_range,final_power",
                  ("gtao", "ue4"): "radius,thickness_heuristic,final_power", ("gtao", "hdrp"): "radius,final_power"}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--method", default="gtao", choices=("gtao", "hbao"))
    p.add_argument("--variant", default="exact", choices=("exact", "hdrp", "ue4"), help="GTAO variant")
    p.add_argument("--params", default=None, help="comma-separated parameters to fit (default: per variant)")
    p.add_argument("--init", default="", help="initial values, e.g. radius=1.0,falloff_range=0.3 (radius in units of R)")
    p.add_argument("--preset", default="high", help="quality preset (slices x steps per side)")
    p.add_argument("--reference", nargs="+", metavar="FILE.npz", help="your own training G-buffers with an 'ao' reference")
    p.add_argument("--holdout", nargs="+", metavar="FILE.npz", help="your own held-out references")
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes")
    p.add_argument("--train-views", type=int, default=2, help="randomised training views per scene")
    add_view_options(p, size="96x64", radius_note="")
    p.add_argument("--steps", type=int, default=30, help="optimizer steps")
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--batch-views", type=int, default=0, help="views per step (0 = all: the best step is then chosen on the whole set)")
    add_run_options(p, out="runs/tune_gtao", hard_every=False)
    p.add_argument("--tiny", action="store_true", help="smoke-test settings (options left at their defaults are replaced): 2 scenes, 32x24, 16 spp, 8 steps")
    return apply_tiny(p, p.parse_args(argv), scenes="sphere_on_plane,room_corner", train_views=1, size="32x24", spp=16, steps=8, preset="medium")


def make(args, **values):
    """The shipped pipeline: the method with ``values`` followed by the denoiser (unless ``--no-denoise``)."""
    kwargs = dict(preset=args.preset, radius=args.max_distance)
    if args.method == "gtao":
        kwargs["variant"] = args.variant
    kwargs.update(values)
    return FittedPipeline(args.method, kwargs, denoiser=not args.no_denoise).to(args.device)


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.manual_seed(args.seed)
    R = args.max_distance
    params = (args.params or DEFAULT_PARAMS.get((args.method, args.variant))
              or ",".join(n for n in fittable_parameters(make(args)) if n != "albedo"))
    params = tuple(s.strip() for s in params.split(",") if s.strip())
    init = {}
    if args.method == "gtao" and args.variant == "exact" and "falloff_range" in params:
        init["falloff_range"] = 0.25  # falloff 0 is a hard cut at the radius: no gradient to radius or falloff
    for item in filter(None, args.init.split(",")):
        key, value = item.split("=")
        init[key.strip()] = float(value) * (R if key.strip() == "radius" else 1.0)

    train, held = build_views(args)
    print(f"{args.method} ({args.variant if args.method == 'gtao' else 'default'}), preset {args.preset}: fitting "
          f"{', '.join(params)} on {len(train)} views, {len(held)} held-out views, R = {R:g}")

    rows = {"default": (make(args), {})}
    if args.method == "gtao" and args.variant == "exact":
        xe = dict(radius=XEGTAO["radius_multiplier"] * R, falloff_range=XEGTAO["falloff_range"], final_power=XEGTAO["final_power"])
        rows["XeGTAO auto-tune"] = (make(args, **xe), xe)
    module = make(args, **init)
    rows["fit start"] = (make(args, **init), init)
    results = {name: {"values": {k: float(v) for k, v in vals.items()}, **evaluate(m, held)} for name, (m, vals) in rows.items()}

    out = Path(args.out)
    cfg = FitConfig(params=params, steps=args.steps, lr=args.lr, batch_views=args.batch_views, seed=args.seed)
    fitted = fit(module, train, cfg, checkpoint=out / "checkpoint.pt", progress=not args.no_progress)
    values = {n: float(p.detach()) for n, p in module.method.named_parameters() if n in params}
    results["fitted"] = {"values": values, **evaluate(module, held)}

    print("\nparameter          " + "".join(f"{n:>18}" for n in results))
    names = sorted({k for r in results.values() for k in r["values"]} | set(params))
    for key in names:
        cells = []
        for name, r in results.items():
            v = r["values"].get(key, float(getattr((rows[name][0] if name in rows else module).method, key).detach()))
            cells.append(f"{(v / R if key == 'radius' else v):18.3f}")
        print(f"{key + (' (x R)' if key == 'radius' else ''):<19}" + "".join(cells))
    print(f"\n{'held-out views, hard mode':<26}{'MAE':>8}{'RMSE':>8}{'PSNR':>8}{'SSIM':>8}{'ms':>8}")
    for name, r in results.items():
        print(f"{name:<26}{r['mae']:8.4f}{r['rmse']:8.4f}{r['psnr']:8.2f}{r['ssim']:8.4f}{r['seconds'] * 1e3:8.1f}")

    payload = {"method": args.method, "variant": args.variant, "preset": args.preset, "max_distance": R,
               "params": list(params), "steps": fitted.steps_done, "fit_seconds": fitted.seconds,
               "radius_multiplier": values.get("radius", float(module.method.radius.detach())) / R,
               "denoiser": not args.no_denoise,
               "xegtao": XEGTAO, "results": results, "history": fitted.history}
    save_json(out / "gtao.json", payload)
    module.save(out / "params.json", holdout_after=results["fitted"])
    print(f"\nwrote {out / 'gtao.json'}, {out / 'params.json'}")
    return payload


if __name__ == "__main__":
    main()

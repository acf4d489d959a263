"""Fit one bitmask-AO thickness per object (through the G-buffer's ``object_id``) and compare with one scalar.

What it does
    Bitmask AO assumes every occluder is ``thickness`` deep behind its visible surface. A scene has
    thin things (fence slats, poles, chair legs) and thick ones (walls, boxes, spheres), so one
    number is a compromise. :class:`~torch_ao.methods.bitmask.BitmaskAO` also takes a ``(K,)``
    table, read at each *sample* by its ``object_id`` -- one thickness per object. This script fits
    that table with :func:`torch_ao.fit.fit` (soft bitmask, followed by the denoiser an engine runs
    after it: a :class:`torch_ao.fitted.FittedPipeline`), fits a single scalar on the same views for
    comparison, keeps for each the values best in *hard* mode on the training views, and prints the
    fitted table and the held-out error of both in hard mode. The per-object pipeline goes to
    ``OUT/params.json`` (its table is indexed by the ids the fit saw: object classes with ``--group
    class``, your engine's ids with ``--group id``).

    Object ids of the built-in scenes (``--group class``, the default) are mapped to object
    *classes* that keep their meaning from one randomised view to the next -- what an engine's
    material id would be: ``plane`` (floors and walls), ``box``, ``thin box`` (slats, seats:
    smallest extent below ``--thin``), ``sphere``, ``cylinder``, ``thin cylinder`` (poles, legs),
    ``mesh``. ``--group id`` keeps the raw ids (use it with your own G-buffers, whose ids your
    engine wrote, or with one fixed scene layout).

How to run
    python training_examples/fit_object_thickness.py                 # about 6 minutes of CPU time on 2 cores
    python training_examples/fit_object_thickness.py --scenes fence,poles,floating --steps 60
    Re-running the same command resumes from ``OUT/checkpoint-*.pt``. Results: ``OUT/object_thickness.json``.

How to adapt
    * Your own G-buffers with ``object_id`` and an ``ao`` reference: ``--reference a.npz b.npz
      --holdout c.npz --group id`` (the table has ``max id + 1`` entries; ids never seen keep the
      initial value).
    * In code::

          module = BitmaskAO(preset="medium", radius=R, thickness=torch.full((K,), 0.5))
          fit(module, views, FitConfig(params=("thickness",)))   # views' gbuffer.object_id in [0, K)
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from torch_ao.datasets import HOLDOUT_SEED, TRAIN_SCENES
from torch_ao.fit import FitConfig, FitView, evaluate, fit
from torch_ao.io import save_json
from torch_ao.reference import Box, Cylinder, Mesh, Plane, Sphere, get_scene

from common import add_bitmask_fit_options, add_run_options, add_view_options, apply_tiny, bitmask
from common import build_views as shared_views

CLASSES = ("background", "plane", "box", "thin box", "sphere", "cylinder", "thin cylinder", "mesh")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--reference", nargs="+", metavar="FILE.npz", help="your own training G-buffers (with object_id and 'ao')")
    p.add_argument("--holdout", nargs="+", metavar="FILE.npz", help="your own held-out references")
    p.add_argument("--group", default=None, choices=("class", "id"),
                   help="per object class (built-in scenes) or raw object id (default: class for built-in scenes, id for --reference)")
    p.add_argument("--thin", type=float, default=0.15, help="'thin' objects: smallest extent below this (world units)")
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes")
    p.add_argument("--train-views", type=int, default=2, help="randomised training views per scene")
    add_view_options(p, size="64x48")
    add_bitmask_fit_options(p, init_help="initial thickness (every object, and the scalar)", steps_help="optimizer steps (each fit)")
    add_run_options(p, out="runs/fit_object_thickness")
    p.add_argument("--tiny", action="store_true", help="smoke-test settings (options left at their defaults are replaced): 2 scenes, 32x24, 16 spp, 6 steps")
    args = apply_tiny(p, p.parse_args(argv), scenes="fence,floating", train_views=1, size="32x24", spp=16, steps=6,
                      preset="low")
    if args.group is None:
        args.group = "id" if args.reference else "class"
    return args


def object_class(obj, thin: float) -> int:
    """Index in :data:`CLASSES` of a scene primitive."""
    if isinstance(obj, Plane):
        return CLASSES.index("plane")
    if isinstance(obj, Box):
        smallest = 2 * min(obj.half_extents)
        return CLASSES.index("thin box" if smallest < thin else "box")
    if isinstance(obj, Sphere):
        return CLASSES.index("sphere")
    if isinstance(obj, Cylinder):
        return CLASSES.index("thin cylinder" if 2 * obj.radius < thin else "cylinder")
    if isinstance(obj, Mesh):
        return CLASSES.index("mesh")
    raise TypeError(f"unknown primitive {type(obj).__name__}")


def by_class(view: FitView, scene: str, seed: int, thin: float) -> FitView:
    """``view`` with its object ids replaced by the class ids of the scene's primitives."""
    objects = get_scene(scene, seed).objects
    lut = torch.zeros(max(o.object_id for o in objects) + 1, dtype=torch.long)
    for o in objects:
        lut[o.object_id] = object_class(o, thin)
    ids = lut.to(view.gbuffer.object_id.device)[view.gbuffer.object_id]
    return FitView(dataclasses.replace(view.gbuffer, object_id=ids), view.reference, view.stderr, view.name)


def build_views(args):
    """The shared views (see common.py), each object id mapped to its class with ``--group class``."""
    train, held = shared_views(args)
    if args.reference:
        for v in train + held:
            if v.gbuffer.object_id is None:
                raise SystemExit(f"error: --reference: {v.name} has no object_id array")
        return train, held
    if args.group == "class":
        scenes = [s for s in args.scenes.split(",") if s]
        train_seeds = list(range(1, args.train_views + 1))
        held_seeds = list(range(HOLDOUT_SEED, HOLDOUT_SEED + args.holdout_views))
        pairs = [(s, k) for s in scenes for k in train_seeds], [(s, k) for s in scenes for k in held_seeds]
        train = [by_class(v, s, k, args.thin) for v, (s, k) in zip(train, pairs[0])]
        held = [by_class(v, s, k, args.thin) for v, (s, k) in zip(held, pairs[1])]
    return train, held


def main(argv=None) -> dict:
    args = parse_args(argv)
    train, held = build_views(args)
    K = int(max(int(v.gbuffer.object_id.max()) for v in train + held)) + 1
    names = list(CLASSES[:K]) if args.group == "class" else [f"id {i}" for i in range(K)]
    print(f"bitmask ({args.preset}, {args.weighting}): fitting a {K}-entry thickness table ({args.group}) on "
          f"{len(train)} views, evaluating on {len(held)} held-out views")

    # Share of valid training pixels per entry (an entry no view shows cannot be fitted).
    counts = torch.zeros(K)
    for v in train:
        counts += torch.bincount(v.gbuffer.object_id[v.gbuffer.valid].cpu(), minlength=K)[:K].float()

    out = Path(args.out)
    rows = {f"scalar start ({args.init:g})": evaluate(bitmask(args, args.init), held)}
    cfg = FitConfig(params=("thickness",), steps=args.steps, lr=args.lr, batch_views=args.batch_views, seed=args.seed,
                    hard_every=args.hard_every)

    scalar = bitmask(args, args.init)
    res_scalar = fit(scalar, train, cfg, checkpoint=out / "checkpoint-scalar.pt", progress=not args.no_progress)
    t_scalar = float(scalar.method.thickness.detach())
    rows[f"scalar fitted ({t_scalar:.3f})"] = evaluate(scalar, held)

    table = bitmask(args, torch.full((K,), args.init))
    res_table = fit(table, train, cfg, checkpoint=out / "checkpoint-table.pt", progress=not args.no_progress)
    values = table.method.thickness.detach().cpu().tolist()
    rows["per-object fitted"] = evaluate(table, held)
    table.save(out / "params.json", names=names, group=args.group, holdout_after=rows["per-object fitted"])

    print(f"\n{'object':<16}{'thickness':>10}{'pixels':>9}")
    for i in range(K):
        if counts[i] > 0:
            print(f"{names[i]:<16}{values[i]:10.3f}{counts[i] / counts.sum():9.1%}")
    print(f"{'(one scalar)':<16}{t_scalar:10.3f}")
    print(f"\n{'held-out views, hard mode':<26}{'MAE':>8}{'RMSE':>8}{'PSNR':>8}{'SSIM':>8}")
    for name, r in rows.items():
        print(f"{name:<26}{r['mae']:8.4f}{r['rmse']:8.4f}{r['psnr']:8.2f}{r['ssim']:8.4f}")

    payload = {"group": args.group, "names": names, "table": values, "pixel_share": (counts / counts.sum()).tolist(),
               "scalar": t_scalar, "init": args.init, "preset": args.preset, "weighting": args.weighting,
               "radius": args.max_distance, "holdout": rows, "steps": [res_scalar.steps_done, res_table.steps_done],
               "fit_seconds": res_scalar.seconds + res_table.seconds}
    save_json(out / "object_thickness.json", payload)
    print(f"\nwrote {out / 'object_thickness.json'}, {out / 'params.json'}")
    return payload


if __name__ == "__main__":
    main()

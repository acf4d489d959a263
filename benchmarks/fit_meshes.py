"""Fitted pipelines on real meshes: docs/accuracy.md, "Real meshes", "Default against fitted".

For each mesh file (normalised to unit size, resting on a floor, as in the "Real meshes" report):

* held-out view: the view :func:`torch_ao.reference.mesh_scene` frames it with, the report's view;
* training views: that view turned ``+-TURN`` degrees about the vertical through the mesh's centre, so the
  fit never sees the held-out camera;

all ray-traced once (cosine-weighted AO within R, with the back-face layer) into ``--cache``. Then one
``torch-ao fit --reference TRAIN... --holdout HELD...`` per pipeline (every mesh's training views together:
one fitted pipeline for all meshes, as for the built-in scenes), each into ``--out/<name>/``, and a table of
held-out PSNR per mesh, default against fitted.

    M=/usr/share/assimp/models
    OMP_NUM_THREADS=1 python benchmarks/fit_meshes.py $M/OBJ/regr01.obj $M/glTF2/ClearCoat-glTF/ClearCoatTest.gltf \\
        $M/STL/sphereWithHole.stl $M/OBJ/box_longline.obj --out runs/fit_meshes
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

#: name -> the ``torch-ao fit`` flags of the pipeline (R and the views are added).
PIPELINES = {
    "bitmask": ["--method", "bitmask"],
    "bitmask_backface_edge": ["--method", "bitmask", "--thickness", "backface", "--fetch", "edge_aware"],
    "exact_backface_edge": ["--method", "bitmask", "--variant", "exact", "--thickness", "backface", "--fetch", "edge_aware"],
    "gtao": ["--method", "gtao"],
    "gtao_edge": ["--method", "gtao", "--fetch", "edge_aware"],
}


def turned(view, degrees: float):
    """``view`` (a LookAt) with its eye turned ``degrees`` about the vertical axis through its target."""
    from torch_ao.reference import LookAt

    (ex, ey, ez), (tx, _, tz) = view.eye, view.target
    a = math.radians(degrees)
    dx, dz = ex - tx, ez - tz
    eye = (tx + dx * math.cos(a) + dz * math.sin(a), ey, tz - dx * math.sin(a) + dz * math.cos(a))
    return LookAt(eye=eye, target=tuple(view.target), up=tuple(view.up), fov_y_degrees=view.fov_y_degrees)


def render_views(files, args) -> tuple[list[Path], list[Path]]:
    """(training files, held-out files) of every mesh, rendered once into ``--cache``."""
    from torch_ao.reference import look_at, mesh_scene, render_reference

    w, h = (int(x) for x in args.size.lower().split("x"))
    train, held = [], []
    for f in map(Path, files):
        if not f.exists():
            raise SystemExit(f"error: mesh file {f} does not exist (apt-get install assimp-testmodels)")
        scene = mesh_scene([f], ground_plane=True, normalize=True)
        for tag, degrees in (("held", 0.0), ("train_a", args.turn), ("train_b", -args.turn)):
            path = Path(args.cache) / f"{f.stem}_{tag}_{w}x{h}_spp{args.spp}_R{args.radius:g}.npz"
            if not path.exists():
                t0 = time.perf_counter()
                v = turned(scene.view, degrees)
                ref = render_reference(scene, look_at(v.eye, v.target, v.up, v.fov_y_degrees, height=h, width=w),
                                       spp=args.spp, max_distance=args.radius, seed=0, uniform=False, backface=True,
                                       progress=False)
                path.parent.mkdir(parents=True, exist_ok=True)
                ref.save(path)  # atomic
                print(f"  rendered {path.name}: {time.perf_counter() - t0:.1f} s")
            (held if tag == "held" else train).append(path)
    return train, held


def table(out: Path, names) -> str:
    """Held-out PSNR per mesh: each pipeline's default and fitted, from the fits' params.json."""
    results = {n: json.loads((out / n / "params.json").read_text()) for n in names}
    views = list(next(iter(results.values()))["per_view"]["fitted"])
    head = "| pipeline | fitted parameters | " + " | ".join(Path(v).name.split("_held")[0] for v in views) + " | mean |"
    lines = [head, "| --- | --- |" + " ---: |" * (len(views) + 1)]
    for n, r in results.items():
        params = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in r["parameters"].items())
        for label in ("default", "fitted"):
            psnr = [r["per_view"][label][v]["psnr"] for v in views]
            lines.append(f"| {n} {label} | {params if label == 'fitted' else ''} | "
                         + " | ".join(f"{p:.2f}" for p in psnr) + f" | {sum(psnr) / len(psnr):.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("meshes", nargs="+", help="mesh files (OBJ, STL, glTF...)")
    p.add_argument("--pipelines", default=",".join(PIPELINES), help=f"comma-separated, of {', '.join(PIPELINES)}")
    p.add_argument("--size", default="160x96", help="render size WxH")
    p.add_argument("--spp", type=int, default=512, help="reference rays per pixel")
    p.add_argument("--radius", type=float, default=0.25, help="R in world units (the meshes are unit size)")
    p.add_argument("--turn", type=float, default=70.0, help="training views' turn from the held-out view, degrees")
    p.add_argument("--preset", default="high")
    p.add_argument("--loss", default="l1")
    p.add_argument("--cache", default="refs/meshes_fit", help="folder of the rendered views")
    p.add_argument("--out", default="runs/fit_meshes", help="one folder per fitted pipeline, and table.md")
    args = p.parse_args(argv)
    names = [n for n in args.pipelines.split(",") if n]
    unknown = set(names) - set(PIPELINES)
    if unknown:
        raise SystemExit(f"error: --pipelines: unknown {', '.join(sorted(unknown))}; expected of {', '.join(PIPELINES)}")
    from torch_ao.cli import main as cli

    train, held = render_views(args.meshes, args)
    out = Path(args.out)
    for n in names:
        t0 = time.perf_counter()
        rc = cli(["fit", *PIPELINES[n], "--preset", args.preset, "--loss", args.loss, "--no-progress",
                  "--reference", *map(str, train), "--holdout", *map(str, held), "--out", str(out / n)])
        if rc:
            return rc
        print(f"fit {n}: {time.perf_counter() - t0:.0f} s")
    md = table(out, names)
    (out / "table.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

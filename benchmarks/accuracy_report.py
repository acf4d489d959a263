"""Accuracy of every method at every preset against the ray-traced reference AND the screen-space truth.

For held-out views of the built-in scenes (320x180, R = 0.5, cosine-weighted reference), every method at
every preset with default parameters, with and without the denoiser, is scored (PSNR/MAE/SSIM, mean signed
error) against

* the ray-traced reference (what a user sees), and
* the screen-space truth of the same thickness (:func:`torch_ao.screen_truth.screen_space_truth`: the same
  depth buffer, the same thickness model, brute force): what the estimator itself adds.

The truth against the reference is what the screen cannot know. A section "convergence of bitmask AO"
measures bitmask AO (cosine sectors, thickness 0.05 and 0.5, without and with jitter, and with options
toggled from outside) against the truth of its thickness from ``low`` to ``reference`` on fence and stairs.
Writes the markdown report (``docs/accuracy.md``) and a plot of error against preset.

    python benchmarks/accuracy_report.py                 # the real report (about 30 min on 1 CPU thread)
    python benchmarks/accuracy_report.py --quick --out /tmp/acc.md --png /tmp/acc.png   # a few minutes
    python benchmarks/accuracy_report.py --mesh /usr/share/assimp/models/OBJ/regr01.obj ... --out meshes.md
        # the "Real meshes" section: one view per mesh file instead of the built-in scenes

With ``--mesh``, each file is normalised to unit size (largest extent 1) resting on a floor, seen from the
view :func:`torch_ao.reference.mesh_scene` frames it with, and R is ``--mesh-radius`` times that size.

Rows come from :func:`pipeline_rows` over a list of :class:`Pipeline` (name, module, denoiser), so fitted
pipelines are added as rows the same way as the defaults (:func:`default_pipelines`).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import shlex
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from torch_ao import Denoiser, PRESETS
from torch_ao.bench import make_method
from torch_ao.datasets import HOLDOUT_SEED, reference_view
from torch_ao.fit import FitView
from torch_ao.methods import get_method
from torch_ao.screen_truth import ScreenTruth, screen_space_truth, split_error

#: Methods scored by default. SSILVB is left out: its visibility is bitmask AO's (it adds indirect light).
METHODS = ("ssao", "hbao", "ue4_ssao", "gtao", "pssao", "bitmask")
SCENES = ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")
CONVERGENCE_SCENES = ("fence", "stairs")


@dataclass
class Settings:
    """A report's size."""

    scenes: tuple[str, ...]
    presets: tuple[str, ...]
    height: int
    width: int
    spp: int  # rays per pixel of the ray-traced reference
    rays: int  # rays per pixel of the screen-space truth
    radius: float = 0.5
    convergence_scenes: tuple[str, ...] = CONVERGENCE_SCENES
    convergence_presets: tuple[str, ...] = tuple(PRESETS)


FULL = Settings(SCENES, tuple(PRESETS), 180, 320, 1024, 512)
QUICK = Settings(("fence", "stairs"), ("low", "high", "extreme"), 48, 80, 64, 64,
                 convergence_presets=("low", "high", "extreme"))


@dataclass
class Pipeline:
    """One row source: a module (evaluated in hard mode, without gradients) and an optional denoiser.
    ``thickness`` is the thickness model of the screen-space truth it is compared with (default: the
    module's ``thickness`` if it has one, else infinite: the horizon methods' assumption)."""

    name: str
    module: nn.Module
    denoiser: Denoiser | None = None
    preset: str = ""
    thickness: object = None
    truth_options: dict = field(default_factory=dict)

    def truth_thickness(self):
        if self.thickness is not None:
            return self.thickness
        t = getattr(self.module, "thickness", None)
        if isinstance(t, torch.Tensor):
            return float(t) if t.dim() == 0 else t.detach()
        return math.inf


def default_pipelines(methods=METHODS, presets=tuple(PRESETS), radius: float = 0.5, denoise=(False, True)) -> list[Pipeline]:
    """Every method at every preset with default parameters (radius = ``radius``), without and with the
    default :class:`~torch_ao.Denoiser`."""
    out = []
    for name in methods:
        for preset in presets:
            module = make_method(get_method(name), preset, radius=radius)
            out += [Pipeline(name, module, Denoiser() if d else None, preset) for d in denoise]
    return out


class Truths:
    """Screen-space truths of each view (by name), computed once per thickness."""

    def __init__(self, radius: float, rays: int, log=print, cache_dir: str | Path | None = None, **kwargs):
        self.radius, self.rays, self.log, self.kwargs = radius, rays, log, kwargs
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self._cache: dict = {}
        self.seconds = 0.0

    @staticmethod
    def _key(thickness):
        if isinstance(thickness, torch.Tensor):
            return ("tensor", tuple(thickness.shape), float(thickness.double().sum()), float(thickness.double().square().sum()))
        return repr(thickness) if callable(thickness) else float(thickness)

    def get(self, view: FitView, thickness, options: dict | None = None) -> ScreenTruth:
        options = dict(options or {})
        key = (view.name, self._key(thickness), tuple(sorted(options.items())))
        if key in self._cache:
            return self._cache[key]
        # Thin occluders need points closer than the thickness along each ray.
        thin = not isinstance(thickness, torch.Tensor) and float(getattr(thickness, "thickness", thickness)) < 0.2
        kwargs = {**(dict(min_steps=64) if thin else {}), **self.kwargs, **options}
        shape = "x".join(map(str, view.gbuffer.depth.shape[-2:]))
        path = None
        if self.cache_dir is not None and not isinstance(thickness, torch.Tensor):
            opts = "-".join(f"{k}{v}" for k, v in sorted(kwargs.items()))
            path = self.cache_dir / (f"truth-{view.name.replace('/', '-')}-{shape}-R{self.radius:g}-t{_fmt_t(thickness)}"
                                     f"-rays{self.rays}-{opts}.pt")
        if path is not None and path.exists():
            self._cache[key] = ScreenTruth(**torch.load(path, weights_only=True))
            return self._cache[key]
        t0 = time.perf_counter()
        truth = screen_space_truth(view.gbuffer, self.radius, thickness, rays=self.rays, **kwargs)
        dt = time.perf_counter() - t0
        self.seconds += dt
        self.log(f"  truth {view.name} thickness={_fmt_t(thickness)}: {dt:.1f} s")
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(dict(vars(truth)), path)
        self._cache[key] = truth
        return truth


class AlongCameraRay:
    """A thickness model for the truth: ``thickness`` measured along each texel's camera ray instead of the
    view axis (depth thickness ``thickness * depth / distance``), close to bitmask AO's push of each sample
    along the view vector."""

    def __init__(self, thickness: float):
        self.thickness = float(thickness)

    def __call__(self, gbuffer):
        return self.thickness * gbuffer.safe_depth / gbuffer.positions().norm(dim=1, keepdim=True)

    def __repr__(self) -> str:
        return f"ray{self.thickness:g}"


def _fmt_t(t) -> str:
    if isinstance(t, torch.Tensor):
        return f"tensor{tuple(t.shape)}"
    if callable(t):
        return repr(t)
    return "inf" if math.isinf(float(t)) else f"{float(t):g}"


@torch.no_grad()
def pipeline_rows(pipelines: list[Pipeline], views: list[FitView], truths: Truths, log=print) -> list[dict]:
    """One row per (pipeline, view): metrics against the reference (``ref_*``) and against the screen-space
    truth of the pipeline's thickness (``truth_*``), the truth against the reference (``screen_*``), the
    truth's mean standard error and the run time."""
    rows = []
    outputs: dict = {}  # a module shared by several pipelines (without and with a denoiser) runs once per view
    for p in pipelines:
        p.module.eval()
        for view in views:
            gb, valid = view.gbuffer, view.gbuffer.valid
            key = (id(p.module), view.name)
            if key not in outputs:
                t0 = time.perf_counter()
                outputs[key] = (p.module(gb).visibility, (time.perf_counter() - t0) * 1e3)
            vis, ms = outputs[key]
            if p.denoiser is not None:
                t0 = time.perf_counter()
                vis = p.denoiser(vis, gb).visibility
                ms += (time.perf_counter() - t0) * 1e3
            truth = truths.get(view, p.truth_thickness(), p.truth_options)
            split = split_error(vis, truth, view.reference, valid)[0]
            row = {"pipeline": p.name, "preset": p.preset, "truth_options": dict(p.truth_options),
                   "denoise": p.denoiser is not None, "scene": view.name, "thickness": _fmt_t(p.truth_thickness()),
                   "ms": ms, "truth_stderr": split.truth_stderr}
            for prefix, m in (("ref", split.total), ("truth", split.estimator), ("screen", split.screen)):
                row.update({f"{prefix}_{k}": v for k, v in m.items()})
            rows.append(row)
        log(f"  {p.name} {p.preset}{' +denoise' if p.denoiser is not None else ''}: "
            f"truth PSNR {statistics.mean(r['truth_psnr'] for r in rows[-len(views):]):.2f} dB")
    return rows


def screen_rows(views: list[FitView], truths: Truths, thicknesses) -> list[dict]:
    """The screen-space truth of each thickness against the ray-traced reference, per view."""
    out = []
    for t in thicknesses:
        for view in views:
            truth = truths.get(view, t)
            split = split_error(truth.visibility, truth, view.reference, view.gbuffer.valid)[0]
            ref_se = float(view.stderr[view.gbuffer.valid].mean()) if view.stderr is not None else float("nan")
            out.append({"scene": view.name, "thickness": _fmt_t(t), **split.screen, "truth_stderr": split.truth_stderr,
                        "ref_stderr": ref_se})
    return out


# ------------------------------------------------------------------------------------------ convergence
#: Bitmask AO configurations of the convergence study: label -> constructor options (cosine sectors).
CONVERGENCE_CONFIGS = {
    "ceil, no jitter": dict(jitter=False),
    "ceil, jitter": dict(jitter=True),
    "round, no jitter": dict(jitter=False, rounding="round"),
    "floor, no jitter": dict(jitter=False, rounding="floor"),
    "ceil, sector_epsilon 0": dict(jitter=False, sector_epsilon=0.0),
    "ceil, nearest fetch": dict(jitter=False, fetch="nearest"),
}


#: Other truths the plain bitmask AO ("ceil, no jitter") is compared with: label -> (thickness model of T, options).
TRUTH_VARIANTS = {
    "vs truth with thickness along the camera ray": (AlongCameraRay, {}),
    "vs truth counting every point within the projected radius": (float, {"bound": "screen"}),
}


def convergence_rows(views: list[FitView], truths: Truths, presets, thicknesses=(0.05, 0.5), configs=None,
                     radius: float = 0.5, variants=None, log=print) -> list[dict]:
    """Bitmask AO (cosine weighting, hard) of each config at each preset and thickness against the truth
    of that thickness (and against the reference); with ``variants`` (see :data:`TRUTH_VARIANTS`) the first
    config also against those truths."""
    from torch_ao import BitmaskAO

    configs = CONVERGENCE_CONFIGS if configs is None else configs
    pipes = []
    for t in thicknesses:
        for i, (label, opts) in enumerate(configs.items()):
            for preset in presets:
                module = BitmaskAO(preset=preset, radius=radius, thickness=t, weighting="cosine", mode="hard", **opts)
                pipes.append(Pipeline(label, module, None, preset, t))
                if i == 0:
                    for vlabel, (model, options) in (variants or {}).items():
                        pipes.append(Pipeline(f"{label}, {vlabel}", module, None, preset, model(t), options))
    return pipeline_rows(pipes, views, truths, log=log)


@torch.no_grad()
def fetch_study(views: list[FitView], presets, thickness: float = 0.05, rays: int = 64, radius: float = 0.5,
                log=print) -> list[str]:
    """Bitmask AO (cosine, no jitter) with bilinear and nearest fetch against the truths with bilinear fetch
    (skirts across depth edges, what the methods' bilinear fetch reads) and with edge-aware fetch (no skirts),
    and against the reference: one line per (scene, fetch, preset)."""
    from torch_ao import BitmaskAO

    lines = ["| scene | bitmask fetch | preset | vs edge-aware truth: MAE (bias) | vs bilinear truth: MAE (bias) | vs reference: PSNR (bias) |",
             "| --- | --- | --- | ---: | ---: | ---: |"]
    for view in views:
        truths = {f: screen_space_truth(view.gbuffer, radius, thickness, rays=rays, fetch=f, min_steps=64, step_px=1.0)
                  for f in ("edge_aware", "bilinear")}
        for fetch in ("bilinear", "nearest"):
            for preset in presets:
                vis = BitmaskAO(preset=preset, radius=radius, thickness=thickness, weighting="cosine", jitter=False,
                                fetch=fetch)(view.gbuffer).visibility
                cells = []
                for st in truths.values():
                    sp = split_error(vis, st, view.reference, view.gbuffer.valid)[0]
                    cells.append(f"{sp.estimator['mae']:.4f} ({sp.estimator['bias']:+.4f})")
                cells.append(f"{sp.total['psnr']:.2f} ({sp.total['bias']:+.4f})")
                lines.append(f"| {view.name} | {fetch} | {preset} | " + " | ".join(cells) + " |")
                log(lines[-1])
    return lines


# ------------------------------------------------------------------------------------------ tables
def _mean(rows, key):
    vals = [r[key] for r in rows]
    return statistics.mean(vals) if vals else float("nan")


def _group(rows, keys):
    out: dict = {}
    for r in rows:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def method_table(rows, presets) -> list[str]:
    """Mean over scenes per (method, preset, denoise)."""
    lines = ["| method | preset | denoise | ref PSNR | ref MAE | ref SSIM | truth PSNR | truth MAE | truth SSIM | truth bias | ms |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    order = {p: i for i, p in enumerate(presets)}
    groups = _group(rows, ("pipeline", "preset", "denoise"))
    for (name, preset, den), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], order.get(kv[0][1], 99), kv[0][2])):
        lines.append(f"| {name} | {preset} | {'yes' if den else 'no'} | {_mean(rs, 'ref_psnr'):.2f} | {_mean(rs, 'ref_mae'):.4f} | "
                     f"{_mean(rs, 'ref_ssim'):.4f} | {_mean(rs, 'truth_psnr'):.2f} | {_mean(rs, 'truth_mae'):.4f} | "
                     f"{_mean(rs, 'truth_ssim'):.4f} | {_mean(rs, 'truth_bias'):+.4f} | {_mean(rs, 'ms'):.0f} |")
    return lines


def scene_table(rows, preset) -> list[str]:
    """Per scene at one preset: PSNR against the reference / against the truth, without and with denoiser."""
    sel = [r for r in rows if r["preset"] == preset]
    scenes = sorted({r["scene"] for r in sel})
    lines = ["| method | denoise | " + " | ".join(scenes) + " | mean |", "| --- | --- |" + " ---: |" * (len(scenes) + 1)]
    for (name, den), rs in sorted(_group(sel, ("pipeline", "denoise")).items()):
        by = {r["scene"]: r for r in rs}
        cells = [f"{by[s]['ref_psnr']:.2f} / {by[s]['truth_psnr']:.2f}" if s in by else "" for s in scenes]
        lines.append(f"| {name} | {'yes' if den else 'no'} | " + " | ".join(cells)
                     + f" | {_mean(rs, 'ref_psnr'):.2f} / {_mean(rs, 'truth_psnr'):.2f} |")
    return lines


def screen_table(rows) -> list[str]:
    lines = ["| scene | thickness | PSNR | MAE | SSIM | mean signed (truth - ref) | truth stderr | reference stderr |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['thickness']} | {r['psnr']:.2f} | {r['mae']:.4f} | {r['ssim']:.4f} | "
                     f"{r['bias']:+.4f} | {r['truth_stderr']:.4f} | {r['ref_stderr']:.4f} |")
    return lines


def convergence_table(rows, presets) -> list[str]:
    """Per (scene, thickness, config): MAE and mean signed error against the truth at each preset, and
    PSNR against the ray-traced reference."""
    lines = ["| scene | thickness | config | " + " | ".join(presets) + " |", "| --- | --- | --- |" + " ---: |" * len(presets)]
    for (scene, t, label), rs in _group(rows, ("scene", "thickness", "pipeline")).items():
        by = {r["preset"]: r for r in rs}
        cells = [f"{by[p]['truth_mae']:.4f} ({by[p]['truth_bias']:+.4f}) / {by[p]['ref_psnr']:.1f}" if p in by else ""
                 for p in presets]
        lines.append(f"| {scene} | {t} | {label} | " + " | ".join(cells) + " |")
    return lines


def plot(rows, presets, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    xs = list(range(len(presets)))
    for ax, target in zip(axes, ("ref", "truth")):
        for (name, den), rs in sorted(_group(rows, ("pipeline", "denoise")).items()):
            by = _group(rs, ("preset",))
            ys = [_mean(by[(p,)], f"{target}_psnr") if (p,) in by else float("nan") for p in presets]
            ax.plot(xs, ys, marker="o", linestyle="-" if den else "--", label=f"{name}{' +denoise' if den else ''}")
        ax.set_xticks(xs, presets)
        ax.set_title("against the ray-traced reference" if target == "ref" else "against the screen-space truth (same thickness)")
        ax.set_xlabel("preset")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("PSNR (dB), mean over scenes")
    axes[1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def convergence_plot(rows, presets, ax_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _group(rows, ("scene", "thickness"))
    fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 4), sharey=True, squeeze=False)
    for ax, ((scene, t), rs) in zip(axes[0], sorted(groups.items())):
        for (label,), cs in _group(rs, ("pipeline",)).items():
            by = {r["preset"]: r for r in cs}
            ax.plot(range(len(presets)), [by[p]["truth_mae"] if p in by else float("nan") for p in presets], marker="o", label=label)
        ax.set_xticks(range(len(presets)), presets, rotation=30)
        ax.set_title(f"{scene}, thickness {t}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("MAE against the screen-space truth")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(ax_path, dpi=110)
    plt.close(fig)


TRUTH_SECTION = """## The screen-space truth

`torch_ao.screen_truth.screen_space_truth(gbuffer, radius, thickness, rays=..., fetch=..., uniform=...)` is a
brute-force estimator of what a screen-space method *could* get from the G-buffer it is given. For every valid
pixel it traces `rays` stratified rays over the hemisphere around the pixel's normal (cosine-distributed for
the cosine-weighted visibility `(1/pi) int V cos`, uniformly distributed for `(1/(2 pi)) int V` with
`uniform=True`), tests points along each ray up to the distance `R` (one per `step_px` pixels of `R`'s projected
length, at least `min_steps`, one random offset per ray, the last point exactly at `R`) against the depth buffer
as surfaces of the given thickness: a point at depth `-z` that projects to `(u, v)` is inside an occluder when
`depth(u,v) <= -z <= depth(u,v) + T(u,v)`. Rays leaving the screen (and points behind the camera) are
unoccluded; background is visibility 1. It reports a per-pixel standard error from independent groups of
stratified rays, as the ray tracer does.

* **Thickness models** (`thickness_map`): a number (`inf`: the horizon methods' solid-behind-every-surface), a
  `(K,)` table per object id, a `(B,1,H,W)` map, a callable `gbuffer -> map` (new models plug in here), or a
  `backface_depth` buffer used as the back surface. The thickness is measured along the view axis at the sample
  (`depth + T`); bitmask AO pushes each sample along the centre pixel's view vector instead (the
  `AlongCameraRay` model of this script measures it along each texel's camera ray, close to that).
* **A thickness of at least R is infinite, except for surfaces in front of the pixel**: a ray of length `R`
  changes depth by at most `R`, so with `T >= R` it can pass behind a surface only if that surface is nearer to
  the camera than the pixel. On fence and stairs the truths of thickness 0.5 and infinity at R = 0.5 agree; under
  the floating object and the sphere they do not (floating: 17.6 against 22.1 dB, see the first table).
* **Fetch.** `fetch="bilinear"` (the default, and what the methods' default fetch reads) interpolates inverse
  depth between texels: planes are exact, but across a depth edge it makes a *skirt* joining the near surface to
  the far one, and a skirt with a thickness blocks rays that pass behind a thin occluder (measured on a thin plank
  in `tests/test_screen_truth.py`: -0.016 in visibility on average beside a plank of thickness 0.05, at any
  resolution). `fetch="edge_aware"` interpolates only inside 2x2 cells whose depths are within `edge_ratio` and
  uses the nearest texel elsewhere (no skirts; exact on that plank to within noise with `edge_ratio=1.02`).
  `fetch="nearest"` is a staircase of flat tiles that occludes rays grazing a slanted surface (several per cent
  on a floor seen at a grazing angle): only for comparison with methods run with `fetch="nearest"`.
* **Checks** (`tests/test_screen_truth.py`): an infinite plane gives exactly 1; a floor next to an infinite wall
  matches `1 - (acos k - k sqrt(1-k^2))/pi` (cosine) and `(1+k)/2` (uniform) within the reported errors; floor
  pixels beside a thin plank match an exact interval clip of every ray against the plank's slab, integrated over
  a fine grid of directions, for thickness 0.05 and infinity (the two differ by up to 0.2 there); too few steps
  miss the thin slab; the error falls at least as `1/sqrt(rays)` (stratification does better) and the reported
  error is the actual one; thickness 0 occludes nothing.
* **Cost**: about 1.5 M rays/s of 32 points each on one CPU thread of the development machine when idle
  (320x180 at 256 rays per pixel: about 10-30 s per view; it is several times slower on a loaded machine).
  `where=` restricts it to some pixels.
* `bound="screen"` is a diagnostic: every point up to `4 R` along the ray that projects within `R`'s projected
  radius counts, whatever its distance (what a walk over the projected radius sees if it counts each sample's
  occluder whole).

`torch_ao.screen_truth.split_error(method, truth, reference, valid)` returns, per view, the error of the truth
against the reference (`screen`: what the screen cannot know), of the method against the truth (`estimator`: what
the method adds) and of the method against the reference (`total`).
"""


# ------------------------------------------------------------------------------------------ main
def method_sections(rows, srows, presets, png: Path) -> list[str]:
    """The report's sections on the screen-space truth against the reference and on every method."""
    png.parent.mkdir(parents=True, exist_ok=True)
    plot(rows, presets, png)
    md = []
    md += ["## What the screen cannot know: the screen-space truth against the reference", "",
           "Per view: the error of the screen-space truth (the best any screen-space estimator of that thickness "
           "model can do on this depth buffer) against the ray-traced reference. It comes from geometry the depth "
           "buffer does not hold (hidden surfaces, occluders off screen, rays leaving the screen) and from the "
           "thickness model (the scene's real objects are neither infinitely thick nor 0.5 thick).", ""]
    md += screen_table(srows) + [""]
    md += ["## Every method at every preset (mean over scenes)", "",
           "`ref`: against the ray-traced reference; `truth`: against the screen-space truth of the method's "
           "thickness, i.e. the estimator's own error (bias and noise); `truth bias`: mean signed error "
           "(negative = too much occlusion). `ms`: one forward call (and the denoiser), 1 thread, on a shared "
           "machine (indicative only).", ""]
    md += method_table(rows, presets) + [""]
    md += [f"![PSNR against preset]({png.name})", ""]
    for preset in ("high", "extreme", "reference"):
        if preset in presets:
            md += [f"### Per scene at `{preset}`: PSNR against the reference / against the truth", ""]
            md += scene_table(rows, preset) + [""]
    return md


def render_json(args, command: str) -> int:
    """Tables and plot of the method sweep from the rows of earlier runs (e.g. scenes run in parallel)."""
    rows, srows = [], []
    for f in args.render_json:
        data = json.loads(Path(f).read_text())
        rows += data["rows"]
        srows += data["screen"]
    presets = [p for p in PRESETS if any(r["preset"] == p for r in rows)]
    md = [f"Rendered by `{command.strip()}` from {', '.join(args.render_json)}.", ""]
    md += method_sections(rows, srows, presets, Path(args.png))
    Path(args.out).write_text("\n".join(md) + "\n")
    print(f"wrote {args.out}")
    return 0


def load_views(s: Settings, scenes, cache_dir, log=print) -> list[FitView]:
    views = []
    for scene in scenes:
        t0 = time.perf_counter()
        views.append(reference_view(scene, HOLDOUT_SEED, height=s.height, width=s.width, spp=s.spp,
                                    max_distance=s.radius, cache_dir=cache_dir))
        log(f"  reference {scene}: {time.perf_counter() - t0:.1f} s")
    return views


def mesh_views(files, *, height: int, width: int, spp: int, radius: float, cache_dir=None, log=print) -> list[FitView]:
    """One reference view per mesh file (``(B,1,H,W)`` cosine-weighted AO within ``radius`` world units): the
    file normalised to unit size on a ground plane, from its framed view; rendered once into
    ``CACHE/meshes/`` (``cache_dir`` default: torch_ao's cache). Views are named ``mesh:<file stem>``."""
    from torch_ao.fit import load_views as load_files
    from torch_ao.reference import look_at, mesh_scene, render_reference
    from torch_ao.views import default_cache_dir

    views = []
    for f in files:
        f = Path(f)
        if not f.exists():
            raise SystemExit(f"error: --mesh: {f} does not exist")
        path = Path(cache_dir or default_cache_dir()) / "meshes" / (
            f"{f.parent.name}_{f.stem}_{width}x{height}_spp{spp}_R{radius:g}.npz")
        if not path.exists():
            t0 = time.perf_counter()
            scene = mesh_scene([f], ground_plane=True, normalize=True)
            v = scene.view
            ref = render_reference(scene, look_at(v.eye, v.target, v.up, v.fov_y_degrees, height=height, width=width),
                                   spp=spp, max_distance=radius, seed=0, uniform=False, progress=False)
            path.parent.mkdir(parents=True, exist_ok=True)
            ref.save(path)
            log(f"  reference {f.name}: {time.perf_counter() - t0:.1f} s")
        view = load_files([path])[0]
        view.name = f"mesh:{f.stem}"
        views.append(view)
    return views


def mesh_sections(rows, srows, presets, png: Path, command: str, views, s: Settings, files) -> list[str]:
    """The "Real meshes" section of the report: the same tables as the built-in scenes' for the mesh views."""
    png.parent.mkdir(parents=True, exist_ok=True)
    plot(rows, presets, png)
    names = ", ".join(f"`{Path(f).name}`" for f in files)
    md = ["## Real meshes", "",
          f"Generated by `{command.strip()}` ({time.strftime('%Y-%m-%d')}, torch {torch.__version__}, 1 thread). "
          f"One view each of {names} (Debian's assimp-testmodels), each normalised to unit size (largest extent 1) "
          f"resting on a floor plane, seen from the view `torch_ao.reference.mesh_scene` frames it with, at "
          f"{s.width}x{s.height}; R = {s.radius:g} (that fraction of each mesh's size); cosine-weighted "
          f"ray-traced reference with {s.spp} rays per pixel; screen-space truth with {s.rays} rays per pixel. "
          "Every method with radius = R and default parameters, hard mode, without and with the default denoiser.",
          "", "### What the screen cannot know: the screen-space truth against the reference", ""]
    md += screen_table(srows) + [""]
    md += ["### Every method at every preset (mean over the meshes)", "",
           "Columns as for the built-in scenes: `ref` against the ray-traced reference (the total error), `truth` "
           "against the screen-space truth of the method's thickness (what the estimator adds).", ""]
    md += method_table(rows, presets) + [""]
    md += [f"![PSNR against preset, real meshes]({png.name})", ""]
    for preset in ("high", "extreme"):
        if preset in presets:
            md += [f"### Per mesh at `{preset}`: PSNR against the reference / against the truth", ""]
            md += scene_table(rows, preset) + [""]
    return md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: 80x48, 2 scenes, 3 presets, 64 rays")
    ap.add_argument("--out", default="docs/accuracy.md", help="markdown report")
    ap.add_argument("--png", default="docs/accuracy.png", help="plot of error against preset")
    ap.add_argument("--cache-dir", default=None, help="reference cache (default: torch_ao's cache)")
    ap.add_argument("--rays", type=int, default=None, help="rays per pixel of the screen-space truth")
    ap.add_argument("--step-px", type=float, default=0.5, help="screen-space truth: one point per this many pixels")
    ap.add_argument("--truth-cache", default=None, help="folder to keep screen-space truths in (reused by reruns)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rows-json", default=None, help="also write every row to this JSON file")
    ap.add_argument("--no-convergence", action="store_true", help="skip the bitmask convergence study")
    ap.add_argument("--only-convergence", action="store_true", help="only the bitmask convergence study")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes or sets of them (procedural, meshes, fit, "
                    "heldout, benchmark: torch_ao.datasets.SCENE_SETS; default: " + ",".join(SCENES) + ")")
    ap.add_argument("--presets", default=None, help="comma-separated presets of the method sweep (default: all)")
    ap.add_argument("--render-json", nargs="+", default=None,
                    help="only render the method tables and plot from the --rows-json files of earlier runs")
    ap.add_argument("--configs", default=None,
                    help="convergence study: the configurations to run, labels separated by ';' (default: all of "
                         + "; ".join(CONVERGENCE_CONFIGS) + ")")
    ap.add_argument("--thicknesses", default="0.05,0.5", help="convergence study: bitmask thicknesses (comma-separated)")
    ap.add_argument("--fetch-study", action="store_true",
                    help="only the fetch study: bitmask AO (thickness 0.05) with bilinear/nearest fetch against "
                         "skirted and skirt-free truths, fence and stairs")
    ap.add_argument("--truth-variants", action="store_true",
                    help="convergence study: also compare with the truth variants (thickness along the camera ray, "
                         "every point within the projected radius: 4x longer rays)")
    ap.add_argument("--mesh", nargs="+", default=None, metavar="FILE",
                    help="the real-mesh section instead: one view per mesh file (OBJ, PLY, STL, glTF...)")
    ap.add_argument("--mesh-radius", type=float, default=0.25, help="--mesh: R as a fraction of each mesh's size")
    ap.add_argument("--size", default=None, help="--mesh: render size WxH (default 160x96)")
    ap.add_argument("--spp", type=int, default=None, help="--mesh: reference rays per pixel (default 512)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    s = QUICK if args.quick else FULL
    if args.rays is not None:
        s.rays = args.rays
    if args.scenes:
        from torch_ao.datasets import parse_scenes

        try:
            s.scenes = tuple(parse_scenes(args.scenes))
        except ValueError as err:
            raise SystemExit(f"error: {err}") from None
    if args.presets:
        s.presets = tuple(x.strip() for x in args.presets.split(","))
    start = time.perf_counter()
    command = "python benchmarks/accuracy_report.py " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    if args.render_json:
        return render_json(args, command)
    if args.mesh:
        return mesh_report(args, s, command)
    if args.fetch_study:
        views = load_views(s, s.convergence_scenes, args.cache_dir)
        lines = [f"Generated by `{command.strip()}`.", ""] + fetch_study(views, s.convergence_presets)
        Path(args.out).write_text("\n".join(lines) + "\n")
        return 0
    scenes = s.convergence_scenes if args.only_convergence else s.scenes
    print(f"references ({len(scenes)} scenes, {s.width}x{s.height}, {s.spp} rays, R = {s.radius})")
    views = load_views(s, scenes, args.cache_dir)
    truths = Truths(s.radius, s.rays, cache_dir=args.truth_cache, step_px=args.step_px)

    md = [f"# Accuracy: every method against the ray-traced reference and the screen-space truth", "",
          f"Generated by `{command.strip()}` ({time.strftime('%Y-%m-%d')}, torch {torch.__version__}, "
          f"{platform.machine()}, {args.threads} thread(s)).", "",
          f"Held-out views (seed {HOLDOUT_SEED}) of the built-in scenes at {s.width}x{s.height}; cosine-weighted "
          f"ray-traced reference with {s.spp} rays per pixel within R = {s.radius}; every method with radius = R "
          f"and default parameters, hard mode. The screen-space truth (`torch_ao.screen_truth.screen_space_truth`, "
          f"{s.rays} cosine-distributed rays per pixel, bilinear fetch as the methods' default, see "
          f"[the method](#the-screen-space-truth)) uses the thickness of the method it is compared with: "
          f"the horizon methods' infinite thickness, bitmask AO's 0.5.", ""]
    rows, srows = [], []
    if not args.only_convergence:
        print("screen-space truth against the reference")
        srows = screen_rows(views, truths, (math.inf, 0.5))
        print("methods")
        rows = pipeline_rows(default_pipelines(presets=s.presets, radius=s.radius), views, truths)
        md += method_sections(rows, srows, s.presets, Path(args.png))
    crows = []
    if not args.no_convergence:
        print("convergence of bitmask AO")
        cviews = [v for v in views if v.name.split("/")[0] in s.convergence_scenes]
        configs = None
        if args.configs:
            labels = [c.strip() for c in args.configs.split(";")]
            unknown = [c for c in labels if c not in CONVERGENCE_CONFIGS]
            if unknown:
                ap.error(f"--configs: unknown {unknown}; expected some of {list(CONVERGENCE_CONFIGS)}")
            configs = {c: CONVERGENCE_CONFIGS[c] for c in labels}
        thicknesses = tuple(float(t) for t in args.thicknesses.split(","))
        crows = convergence_rows(cviews, truths, s.convergence_presets, thicknesses, configs=configs, radius=s.radius,
                                 variants=TRUTH_VARIANTS if args.truth_variants else None)
        cpng = Path(args.png).with_name(Path(args.png).stem + "_convergence.png")
        convergence_plot(crows, s.convergence_presets, cpng)
        md += ["## Convergence of bitmask AO", "",
               "Bitmask AO with cosine sectors and a fixed thickness against the screen-space truth of the same "
               "thickness: MAE (mean signed error in brackets; negative = too much occlusion) at each preset, "
               "then the PSNR (dB) against the ray-traced reference. "
               "An estimator that converges has an error that falls with the preset down to the truth's noise "
               f"(its mean per-pixel standard error is listed below).", ""]
        md += convergence_table(crows, s.convergence_presets) + [""]
        md += [f"![bitmask MAE against preset]({cpng.name})", ""]
        noise = _group(crows, ("scene", "thickness"))
        md += ["Truth noise (mean per-pixel standard error): " + ", ".join(
            f"{k[0]} t={k[1]}: {_mean(v, 'truth_stderr'):.4f}" for k, v in sorted(noise.items())), ""]
    md += [TRUTH_SECTION, ""]
    md += [f"Total time {time.perf_counter() - start:.0f} s (screen-space truths {truths.seconds:.0f} s).", ""]
    if args.rows_json:
        Path(args.rows_json).write_text(json.dumps({"rows": rows, "screen": srows, "convergence": crows}, indent=1))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(md) + "\n")
    print(f"wrote {out}")
    return 0


def mesh_report(args, s: Settings, command: str) -> int:
    """``--mesh``: every method at every preset on one view per mesh file (the "Real meshes" section)."""
    w, h = (int(x) for x in (args.size or "160x96").lower().split("x"))
    s.width, s.height, s.spp, s.radius = w, h, args.spp or 512, args.mesh_radius
    if args.rays is None:
        s.rays = 256
    print(f"references ({len(args.mesh)} meshes, {w}x{h}, {s.spp} rays, R = {s.radius:g})")
    views = mesh_views(args.mesh, height=h, width=w, spp=s.spp, radius=s.radius, cache_dir=args.cache_dir)
    truths = Truths(s.radius, s.rays, cache_dir=args.truth_cache, step_px=args.step_px)
    srows = screen_rows(views, truths, (math.inf, 0.5))
    rows = pipeline_rows(default_pipelines(presets=s.presets, radius=s.radius), views, truths)
    md = mesh_sections(rows, srows, s.presets, Path(args.png), command, views, s, args.mesh)
    md += [f"Total time {time.perf_counter() - _START:.0f} s (screen-space truths {truths.seconds:.0f} s).", ""]
    if args.rows_json:
        Path(args.rows_json).write_text(json.dumps({"rows": rows, "screen": srows}, indent=1))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(md) + "\n")
    print(f"wrote {out}")
    return 0


_START = time.perf_counter()


if __name__ == "__main__":
    raise SystemExit(main())

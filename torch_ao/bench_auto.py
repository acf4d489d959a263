"""``torch-ao ao --auto``: apply the bench recommendation (cheapest method and preset whose MAE is within a
tolerance of the best) to a G-buffer file, from a saved report or from a quick sweep on the file's own
``ao`` reference."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Callable

from .bench import QUICK, available_methods, load_bench_views, recommend, run_bench

__all__ = ["auto_choice", "apply_auto", "DEFAULT_TOLERANCE"]

DEFAULT_TOLERANCE = 0.01

_NEITHER = ("--auto needs either a bench report (--report REPORT.json, written by `torch-ao bench --out DIR`) "
            "or a G-buffer file with an 'ao' reference array to sweep against (`torch-ao render SCENE --out FILE.npz` "
            "writes one)")


def auto_choice(path: str | os.PathLike | None = None, *, report: str | os.PathLike | None = None,
                tolerance: float | None = None, device="cpu", methods=None, progress: bool = False,
                log: Callable[[str], None] | None = None) -> dict:
    """The recommended ``{"method", "preset", "radius", "scene", "source", "mae", "forward_ms", "best"}``.

    With ``report``: the report's rows, re-ranked with ``tolerance`` (default: the report's), for the
    scene named like ``path``'s stem, else for the mean over the report's scenes (``"all"``).
    Without: a quick sweep (all available methods, presets low..ultra, no denoiser, forward only) on
    ``path``'s ``ao`` reference. Raises ``ValueError`` explaining what is missing when neither is possible.
    """
    from .bench_report import load_report

    if tolerance is not None and not (tolerance >= 0 and math.isfinite(tolerance)):
        raise ValueError(f"--tolerance: expected a finite value >= 0, got {tolerance}")
    stem = Path(path).stem if path else None
    if report is not None:
        data = load_report(report)
        tol = float(data.get("tolerance", DEFAULT_TOLERANCE)) if tolerance is None else float(tolerance)
        rows = data["rows"]
        rec = recommend(rows, tol, denoise=False)
        scene = _match_scene(stem, [k for k in rec if k != "all"])
        scene = scene or ("all" if "all" in rec else (next(iter(rec)) if len(rec) == 1 else None))
        if scene is None:
            raise ValueError(f"--report: {report} has no scene named like {stem or 'the built-in example'} and no "
                             f"configuration that ran on all of its scenes ({', '.join(rec) or 'no rows'}); "
                             "pass a report of a sweep over this file (torch-ao bench --reference FILE)")
        source = f"report {report}" + (f", scene {scene}" if scene != "all" else ", mean over its scenes")
    else:
        if path is None:
            raise ValueError(_NEITHER + "; the built-in example has no reference")
        from .io import read_npz

        if "ao" not in read_npz(path):
            raise ValueError(f"{path} has no 'ao' reference array and no --report was given: " + _NEITHER)
        tol = DEFAULT_TOLERANCE if tolerance is None else float(tolerance)
        views = load_bench_views(files=[path], device=device, progress=progress, log=log)
        found = available_methods(methods, log=log)
        if not found:
            raise ValueError("--auto: no method is available to sweep")
        presets = ["low", "medium", "high", "ultra"]
        rows = run_bench(views, found, presets, denoise=False, backward=False, repeats=QUICK.repeats, device=device,
                         progress=progress, log=log)
        scene = views[0].name
        rec = recommend(rows, tol, denoise=False, include_all=False)
        source = f"quick sweep on {path} ({len(found)} methods x {len(presets)} presets)"
    pick = rec[scene]
    radius = next((float(r["radius"]) for r in rows if r["method"] == pick["method"] and r["preset"] == pick["preset"]
                   and "radius" in r and (scene == "all" or r["scene"] == scene)), None)
    return {"method": pick["method"], "preset": pick["preset"], "radius": radius, "scene": scene, "source": source,
            "tolerance": tol, "mae": pick["mae"], "forward_ms": pick["forward_ms"], "best": pick["best"]}


def _match_scene(stem: str | None, scenes: list[str]) -> str | None:
    """The report scene a file is about: same stem, else the longest scene name the stem starts with
    followed by ``_`` (the cache names ``<scene>_<W>x<H>_...``)."""
    if not stem:
        return None
    if stem in scenes:
        return stem
    prefixed = [s for s in scenes if stem.startswith(s + "_")]
    return max(prefixed, key=len) if prefixed else None


def apply_auto(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    """Set ``args.method``/``args.preset`` (and ``args.radius`` when not given) from :func:`auto_choice`."""
    if not getattr(args, "auto", False):
        raise ValueError("--report/--tolerance: only meaningful with --auto")
    if args.report is None and args.gbuffer:
        log(f"auto: no --report; running a quick sweep on {args.gbuffer}'s reference (all methods, low..ultra)")
    choice = auto_choice(args.gbuffer, report=args.report, tolerance=args.tolerance, device=args.device,
                         progress=True, log=None)
    args.method, args.preset = choice["method"], choice["preset"]
    if getattr(args, "radius", None) is None and choice["radius"] is not None:
        args.radius = choice["radius"]
    b = choice["best"]
    log(f"auto: {choice['method']} preset {choice['preset']} (MAE {choice['mae']:.4f}, {choice['forward_ms']:.1f} ms; "
        f"best {b['method']} {b['preset']} MAE {b['mae']:.4f}; tolerance {choice['tolerance']:g}) from {choice['source']}")
    return choice

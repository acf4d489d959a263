"""The recommendation for one G-buffer file (what ``torch-ao ao --auto`` applies): the cheapest method and
preset whose MAE is within a tolerance of the best, from a saved report or from a quick sweep on the
file's own ``ao`` reference."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from ..checks import check_float
from ..views import load_bench_views
from .files import load_report
from .recommend import DEFAULT_TOLERANCE, recommend
from .sweep import QUICK, available_methods, run_bench

__all__ = ["auto_choice", "AUTO_PRESETS"]

#: Presets of the quick sweep run when there is no report (the @half ones walk a quarter of the pixels).
AUTO_PRESETS = ("low", "medium", "high", "ultra", "high@half", "ultra@half")

_NEITHER = ("--auto needs either a bench report (--report REPORT.json, written by `torch-ao bench --out DIR`) "
            "or a G-buffer file with an 'ao' reference array to sweep against (`torch-ao render SCENE --out FILE.npz` "
            "writes one)")


def auto_choice(path: str | os.PathLike | None = None, *, report: str | os.PathLike | None = None,
                tolerance: float | None = None, device="cpu", methods=None, progress: bool = False,
                log: Callable[[str], None] | None = None) -> dict:
    """The recommended ``{"method", "preset", "radius", "scene", "source", "mae", "forward_ms", "best"}``.

    With ``report``: the report's rows, re-ranked with ``tolerance`` (default: the report's), for the
    scene named like ``path``'s stem, else for the mean over the report's scenes (``"all"``).
    Without: a quick sweep (all available methods, presets low..ultra and high@half, ultra@half, no denoiser, forward only) on
    ``path``'s ``ao`` reference. Raises ``ValueError`` explaining what is missing when neither is possible.
    """
    if tolerance is not None:
        tolerance = check_float("tolerance", tolerance, 0.0)
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
        from ..io import read_npz

        if "ao" not in read_npz(path):
            raise ValueError(f"{path} has no 'ao' reference array and no --report was given: " + _NEITHER)
        tol = DEFAULT_TOLERANCE if tolerance is None else float(tolerance)
        views = load_bench_views(files=[path], device=device, progress=progress, log=log)
        found = available_methods(methods, log=log)
        if not found:
            raise ValueError("--auto: no method is available to sweep")
        presets = list(AUTO_PRESETS)
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

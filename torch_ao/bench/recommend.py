"""Choosing a configuration from sweep rows: the Pareto front of error against cost, the mean over
scenes, and the recommendation (the cheapest configuration whose error is within a tolerance of the best)."""
from __future__ import annotations

import math
import statistics
from typing import Sequence

from ..checks import check_float

__all__ = ["DEFAULT_TOLERANCE", "pareto_front", "aggregate_rows", "recommend"]

#: Allowed MAE above the best of a scene when nothing else is asked for.
DEFAULT_TOLERANCE = 0.01


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points ``(cost, error)`` not dominated by another (lower or equal in both, lower in
    one), sorted by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        c, e = points[i]
        if math.isnan(c) or math.isnan(e):
            continue
        if e < best:
            front.append(i)
            best = e
    return front


def aggregate_rows(rows: Sequence[dict], metric: str = "mae", cost: str = "forward_ms") -> list[dict]:
    """Mean ``metric`` and ``cost`` over scenes per (method, preset, denoise), for configurations run on
    every scene; rows named ``scene="all"``."""
    scenes = {r["scene"] for r in rows}
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], r["preset"], bool(r["denoise"])), []).append(r)
    out = []
    for (method, preset, den), rs in groups.items():
        if {r["scene"] for r in rs} != scenes:
            continue
        row = {"scene": "all", "method": method, "preset": preset, "denoise": den,
               "slices": rs[0].get("slices"), "steps": rs[0].get("steps")}
        for key in ("mae", "rmse", "psnr", "ssim", "forward_ms", "forward_cpu_ms", "forward_backward_ms"):
            vals = [float(r[key]) for r in rs if key in r]
            row[key] = statistics.fmean(vals) if vals else math.nan
        out.append(row)
    return out


def recommend(rows: Sequence[dict], tolerance: float = DEFAULT_TOLERANCE, *, metric: str = "mae", cost: str = "forward_ms",
              denoise: bool | None = False, include_all: bool = True) -> dict[str, dict]:
    """Per scene, the cheapest configuration whose ``metric`` (lower is better; MAE by default) is within
    ``tolerance`` (absolute) of the scene's best.

    Args:
        rows: result rows (:func:`run_bench`, or built by hand: ``scene``, ``method``, ``preset``,
            ``metric`` and ``cost`` keys are enough).
        tolerance: allowed excess error over the best (``0`` = the best configuration).
        denoise: only rows with this ``denoise`` flag (``None`` = all rows).
        include_all: add ``"all"``, the same choice on the mean over scenes (for frames not in the sweep).

    Returns:
        ``{scene: {"method", "preset", "denoise", metric, cost, "best": {...}, "tolerance"}}``.
    """
    tolerance = check_float("tolerance", tolerance, 0.0)
    use = [r for r in rows if denoise is None or bool(r.get("denoise", False)) == denoise]
    use = [r for r in use if not (math.isnan(float(r[metric])) or math.isnan(float(r[cost])))]
    by_scene: dict[str, list[dict]] = {}
    for r in use:
        by_scene.setdefault(str(r["scene"]), []).append(r)
    if include_all and len(by_scene) > 0:
        agg = aggregate_rows(use, metric, cost)
        if agg:
            by_scene["all"] = agg
    out = {}
    for scene, rs in by_scene.items():
        best = min(rs, key=lambda r: (float(r[metric]), float(r[cost])))
        limit = float(best[metric]) + tolerance
        ok = [r for r in rs if float(r[metric]) <= limit + 1e-12]
        pick = min(ok, key=lambda r: (float(r[cost]), float(r[metric])))
        out[scene] = {
            "method": pick["method"], "preset": pick["preset"], "denoise": bool(pick.get("denoise", False)),
            metric: float(pick[metric]), cost: float(pick[cost]),
            "best": {"method": best["method"], "preset": best["preset"], "denoise": bool(best.get("denoise", False)),
                     metric: float(best[metric]), cost: float(best[cost])},
            "tolerance": float(tolerance), "metric": metric, "cost": cost,
        }
    return out

"""Files of a ``torch-ao bench`` report: ``bench.csv``, ``bench.md``, ``report.json`` and plots of error
against run time (``plot_<scene>.png`` per scene and ``plot_all.png`` on the mean over scenes), one
curve per method (dashed: with the denoiser), the Pareto front marked."""
from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
from typing import Sequence

from ..io import write_text_atomic
from ..methods import PRESETS
from ..methods.common import split_preset
from ..resolution import RESOLUTIONS
from .recommend import DEFAULT_TOLERANCE, aggregate_rows, pareto_front, recommend
from .sweep import COLUMNS

__all__ = ["write_report", "write_csv", "markdown_report", "plot_error_vs_time", "load_report", "REPORT_VERSION"]

REPORT_VERSION = 1
_QUALITY_ORDER = {p: i for i, p in enumerate(PRESETS)}
_RESOLUTION_ORDER = {r: i for i, r in enumerate(RESOLUTIONS)}
#: a preset's resolution as the plots mark it
_RESOLUTION_MARK = {"full": "", "half": "½", "quarter": "¼"}


def _preset_parts(preset) -> tuple[str, str]:
    """``(quality, resolution)`` of a row's preset (``"full"`` when it names none; unknown names as given)."""
    try:
        quality, resolution = split_preset(preset)
    except ValueError:
        return str(preset), "full"
    return quality, resolution or "full"


def _preset_key(preset) -> tuple[int, int]:
    """Sort key of a preset: full-resolution presets first, each resolution from low to reference."""
    quality, resolution = _preset_parts(preset)
    return _RESOLUTION_ORDER.get(resolution, 9), _QUALITY_ORDER.get(quality, 99)


def _sorted(rows: Sequence[dict]) -> list[dict]:
    return sorted(rows, key=lambda r: (str(r["scene"]), str(r["method"]), _preset_key(r["preset"]),
                                       bool(r.get("denoise", False))))


def write_csv(path: str | os.PathLike, rows: Sequence[dict]) -> Path:
    """Rows as CSV with the :data:`~torch_ao.bench.sweep.COLUMNS` (then any extra keys)."""
    import io

    extra = sorted({k for r in rows for k in r} - set(COLUMNS))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(COLUMNS) + extra, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in _sorted(rows):
        w.writerow({k: (int(v) if isinstance(v, bool) else v) for k, v in r.items()})
    path = Path(path)
    write_text_atomic(path, buf.getvalue())
    return path


def _fmt(x, digits=4) -> str:
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        if math.isnan(x):
            return "–"
        return f"{x:.{digits}f}" if abs(x) < 1000 else f"{x:.0f}"
    return str(x)


def _ms(x) -> str:
    return _fmt(float(x), 2 if float(x) < 100 else 1)


def _metrics(r: dict) -> list[str]:
    g = lambda k: float(r.get(k, math.nan))  # noqa: E731
    return [_fmt(g("mae")), _fmt(g("rmse")), _fmt(g("psnr"), 2), _fmt(g("ssim"), 3), _ms(g("forward_ms")),
            _ms(g("forward_cpu_ms")), _ms(g("forward_backward_ms"))]


def _size(r: dict) -> str:
    if r.get("slices") is not None and r.get("steps") is not None:
        return f"{r['slices']}x{r['steps']}"
    s = PRESETS.get(_preset_parts(r.get("preset"))[0])
    return f"{s[0]}x{s[1]}" if s else "?"


def _table(header: Sequence[str], lines: Sequence[Sequence]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    out += ["| " + " | ".join(_fmt(c) if not isinstance(c, str) else c for c in line) + " |" for line in lines]
    return out


def _recommendation_table(recommendations: dict) -> list[str]:
    """Markdown lines of :func:`~torch_ao.bench.recommend.recommend`'s choice per scene."""
    lines = [(s, r["method"], r["preset"], _fmt(r["denoise"]), r["mae"], _ms(r["forward_ms"]),
              f"{r['best']['method']} {r['best']['preset']}{' +denoise' if r['best']['denoise'] else ''}",
              r["best"]["mae"]) for s, r in recommendations.items()]
    return _table(("scene", "method", "preset", "denoise", "MAE", "forward ms", "best", "best MAE"), lines)


def markdown_report(rows: Sequence[dict], recommendations: dict, *, background: Sequence[dict] | None = None,
                    env: dict | None = None, command: str | None = None, plots: Sequence[str] = (),
                    tolerance: float | None = None, with_denoiser: dict | None = None) -> str:
    """The markdown summary: environment, recommendation per scene (and, given ``with_denoiser``, the same over
    the rows with the denoiser too), the result table, background timings."""
    md = ["# torch-ao bench", ""]
    if command:
        md += ["```", command, "```", ""]
    if env:
        load = env.get("load_average")
        md += [f"Device: {env.get('device_name', env.get('device'))}, {env.get('threads')} torch threads, "
               f"torch {env.get('torch')}"
               + (f", load average {load[0]:.1f} at the end of the run" if load else "")
               + ". Times are medians of repeated runs after warm-up, in ms: wall time, and the process's CPU time "
               "(all threads; steadier than wall time on a shared machine).", ""]
    if recommendations:
        md += [f"## Recommendation (cheapest forward time with MAE within {tolerance:g} of the best)", ""]
        md += _recommendation_table(recommendations)
        md += ["", "`all`: the same choice on the mean over scenes (used for frames that are not in the sweep). "
               "fwd+bwd is timed in the mode fitting uses (soft for bitmask modules); `–`: no gradient path.", ""]
    if with_denoiser and any(r["denoise"] or r["best"]["denoise"] for r in with_denoiser.values()):
        md += ["### With the denoiser allowed (forward ms include it)", ""]
        md += _recommendation_table(with_denoiser) + [""]
    if rows:
        md += ["## Error against run time", ""]
        lines = [(r["scene"], r["method"], r["preset"], _size(r), _fmt(bool(r.get("denoise", False))),
                  *_metrics(r)) for r in _sorted(rows)]
        md += _table(("scene", "method", "preset", "slices x steps", "denoise", "MAE", "RMSE", "PSNR", "SSIM",
                      "forward ms", "forward CPU ms", "fwd+bwd ms"), lines) + [""]
        agg = aggregate_rows(rows)
        if agg and len({r["scene"] for r in rows}) > 1:
            md += ["### Mean over scenes", ""]
            lines = [(r["method"], r["preset"], _fmt(bool(r["denoise"])),
                      *_metrics(r)) for r in _sorted(agg)]
            md += _table(("method", "preset", "denoise", "MAE", "RMSE", "PSNR", "SSIM", "forward ms", "forward CPU ms",
                          "fwd+bwd ms"), lines) + [""]
    if background:
        md += ["## Background costs nothing", "",
               "Forward time on a full frame, the same frame with its right half background, and all background; "
               "`walked` is the number of pixels the marching core walks (`Frame.queries`).", ""]
        lines = [(f"{b['method']}", f"{b['preset']}", f"{b['frame']} {b['width']}x{b['height']}",
                  f"{b['valid_fraction']:.2f}", str(b["walked_pixels"]),
                  _ms(b["forward_ms"]), f"{b['time_ratio']:.2f}", _ms(b.get("forward_cpu_ms", math.nan)),
                  f"{b.get('cpu_ratio', math.nan):.2f}") for b in background]
        md += _table(("method", "preset", "frame", "valid fraction", "walked", "forward ms", "time / full",
                      "forward CPU ms", "CPU time / full"), lines) + [""]
    if plots:
        md += ["## Plots", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in plots] + [""]
    return "\n".join(md)


#: Legend entries per column of :func:`plot_error_vs_time` (more entries: more columns, so it fits the figure).
_LEGEND_ROWS = 16


def plot_error_vs_time(rows: Sequence[dict], path: str | os.PathLike, *, title: str = "", metric: str = "mae",
                       cost: str = "forward_ms") -> Path:
    """Error against run time (log x), one curve per method and walk resolution through its presets
    (solid: plain, dashed: denoised; at half/quarter resolution thinner, points labelled ``H½``), the
    Pareto front over all points as a black step line with ringed points; the legend to the right,
    inside the image (:func:`error_vs_time_figure`)."""
    import matplotlib.pyplot as plt

    fig = error_vs_time_figure(rows, title=title, metric=metric, cost=cost)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def error_vs_time_figure(rows: Sequence[dict], *, title: str = "", metric: str = "mae", cost: str = "forward_ms"):
    """The matplotlib figure :func:`plot_error_vs_time` saves (the caller closes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.0, 4.4), dpi=100, layout="constrained")
    methods = sorted({r["method"] for r in rows})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, m in enumerate(methods):
        for res, den in ((res, den) for res in RESOLUTIONS for den in (False, True)):
            rs = sorted([r for r in rows if r["method"] == m and bool(r.get("denoise", False)) == den
                         and _preset_parts(r["preset"])[1] == res], key=lambda r: _preset_key(r["preset"]))
            if not rs:
                continue
            xs, ys = [float(r[cost]) for r in rs], [float(r[metric]) for r in rs]
            ax.plot(xs, ys, "--" if den else "-", marker="s" if den else ("o" if res == "full" else "^"), ms=4,
                    color=colors[i % len(colors)], lw=1.5 if res == "full" else 0.8,
                    label=f"{m}{'' if res == 'full' else ' @' + res}{' + denoise' if den else ''}",
                    alpha=0.6 if den else 1.0)
            if not den:
                for x, y, r in zip(xs, ys, rs):
                    quality, _ = _preset_parts(r["preset"])
                    ax.annotate(quality[0].upper() + _RESOLUTION_MARK.get(res, ""), (x, y), textcoords="offset points",
                                xytext=(3, 3), fontsize=6)
    pts = [(float(r[cost]), float(r[metric])) for r in rows]
    front = [pts[i] for i in pareto_front(pts)]
    if front:
        ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k", lw=1, alpha=0.7,
                label="Pareto front")
        ax.scatter([p[0] for p in front], [p[1] for p in front], s=70, facecolors="none", edgecolors="k", lw=1, zorder=5)
    ax.set_xscale("log")
    from matplotlib.ticker import FuncFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda x, _: f"{x:g}" if f"{x:g}"[0] in "25" else ""))
    ax.set_xlabel(f"{cost.replace('_ms', '').replace('_', '+')} time (ms, median)")
    ax.set_ylabel(metric.upper() + " vs reference")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    entries = len(ax.get_legend_handles_labels()[1])
    # "outside": constrained layout shrinks the axes so the legend lies inside the saved image
    fig.legend(fontsize=7, loc="outside right upper", ncols=max(1, math.ceil(entries / _LEGEND_ROWS)))
    return fig


def write_report(out_dir: str | os.PathLike, rows: Sequence[dict], *, tolerance: float = DEFAULT_TOLERANCE,
                 background: Sequence[dict] | None = None, env: dict | None = None, command: str | None = None,
                 settings: dict | None = None, plots: bool = True) -> dict[str, Path]:
    """Write ``bench.csv``, ``bench.md``, ``report.json`` and (``plots``) the PNGs into ``out_dir``.

    ``report.json`` holds the rows, the recommendations (``recommendations``: plain methods, used by
    ``torch-ao ao --auto``; ``recommendations_with_denoiser``: over all rows), the background timings,
    the environment and the settings. Returns ``{kind: path}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = recommend(rows, tolerance, denoise=False)
    rec_any = recommend(rows, tolerance, denoise=None)
    files = {"csv": write_csv(out / "bench.csv", rows)}
    plot_paths = []
    if plots and rows:
        for scene in sorted({r["scene"] for r in rows}):
            plot_paths.append(plot_error_vs_time([r for r in rows if r["scene"] == scene], out / f"plot_{scene}.png",
                                                 title=f"{scene}: MAE against forward time"))
        agg = aggregate_rows(rows)
        if agg:
            plot_paths.append(plot_error_vs_time(agg, out / "plot_all.png",
                                                 title=f"mean over {len({r['scene'] for r in rows})} scenes"))
        for p in plot_paths:
            files[p.stem] = p
    md = markdown_report(rows, rec, background=background, env=env, command=command,
                         plots=[str(p) for p in plot_paths], tolerance=tolerance, with_denoiser=rec_any)
    write_text_atomic(out / "bench.md", md)
    files["md"] = out / "bench.md"
    payload = {"version": REPORT_VERSION, "command": command, "environment": env or {}, "settings": settings or {},
               "tolerance": tolerance, "metric": "mae", "cost": "forward_ms", "recommendations": rec,
               "recommendations_with_denoiser": rec_any, "rows": _sorted(rows), "background": list(background or [])}
    write_text_atomic(out / "report.json", json.dumps(payload, indent=1, default=_json_default, allow_nan=True))
    files["json"] = out / "report.json"
    return files


def _json_default(x):
    if hasattr(x, "item"):
        return x.item()
    return str(x)


def load_report(path: str | os.PathLike) -> dict:
    """A ``report.json`` written by :func:`write_report` (or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / "report.json"
    if not path.is_file():
        raise FileNotFoundError(f"--report: no such file: {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"--report: {path} is not a bench report (invalid JSON: {err})") from None
    if not isinstance(data, dict) or "rows" not in data or "recommendations" not in data:
        raise ValueError(f"--report: {path} is not a bench report (no 'rows'/'recommendations'); "
                         f"write one with `torch-ao bench --out DIR`")
    return data

"""torch-ao bench: report files of a tiny sweep, the recommendation, --auto."""
import csv
import json

import pytest
import torch

from test_bench_helpers import TinyAO
from torch_ao.bench import COLUMNS, aggregate_rows, load_report, make_method, pareto_front, recommend, run_bench, write_report
from torch_ao.views import load_bench_views, reference_path
from torch_ao.cli import main

H, W, SPP = 24, 32, 8


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def views(cache):
    return load_bench_views(["sphere_on_plane"], height=H, width=W, spp=SPP, cache_dir=cache, progress=False, log=None)


def _tiny_methods():
    return {"tiny": TinyAO, "tiny_sq": lambda **kw: TinyAO(step_power=2.0, **kw)}


def test_reference_is_cached(cache, views):
    path = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    assert path.is_file()
    mtime = path.stat().st_mtime_ns
    again = load_bench_views(["sphere_on_plane"], height=H, width=W, spp=SPP, cache_dir=cache, progress=False, log=None)
    assert path.stat().st_mtime_ns == mtime  # read, not rendered again
    assert torch.equal(again[0].reference, views[0].reference) and again[0].max_distance == 1.0


def test_tiny_sweep_report_files(views, tmp_path):
    rows = run_bench(views, _tiny_methods(), ["low", "medium"], repeats=1, warmup=0, progress=False, log=None)
    assert len(rows) == 2 * 2 * 2  # methods x presets x (plain, denoised)
    files = write_report(tmp_path, rows, tolerance=0.01, env={"device": "cpu", "threads": 1})
    for key in ("csv", "md", "json", "plot_sphere_on_plane", "plot_all"):
        assert files[key].is_file() and files[key].stat().st_size > 0, key
    with open(files["csv"]) as f:
        table = list(csv.DictReader(f))
    assert list(table[0])[: len(COLUMNS)] == list(COLUMNS)
    assert len(table) == 8
    assert {(r["method"], r["preset"], r["denoise"]) for r in table} == {
        (m, p, d) for m in ("tiny", "tiny_sq") for p in ("low", "medium") for d in ("0", "1")}
    for r in table:
        assert r["scene"] == "sphere_on_plane" and (r["slices"], r["steps"]) == {"low": ("1", "2"), "medium": ("2", "2")}[r["preset"]]
        assert 0 <= float(r["mae"]) <= 1 and float(r["forward_ms"]) > 0 and float(r["forward_backward_ms"]) > 0
        assert -1 <= float(r["ssim"]) <= 1 and int(r["valid_pixels"]) == H * W
    md = files["md"].read_text()
    assert "Recommendation" in md and "| scene | method | preset |" in md
    assert md.split("## Error against run time")[1].split("##")[0].count("| sphere_on_plane | tiny") == 8
    report = load_report(tmp_path)
    assert len(report["rows"]) == 8 and set(report["recommendations"]) == {"sphere_on_plane", "all"}
    assert report["recommendations"]["sphere_on_plane"]["method"] in ("tiny", "tiny_sq")


def _row(scene, method, preset, mae, ms, denoise=False):
    return {"scene": scene, "method": method, "preset": preset, "mae": mae, "forward_ms": ms, "denoise": denoise}


def test_report_recommends_with_the_denoiser_too_when_a_denoised_row_wins(tmp_path):
    from torch_ao.bench.files import markdown_report

    rows = [_row("s", "gtao", "high", 0.040, 4.0), _row("s", "bitmask", "high", 0.045, 8.0),
            _row("s", "bitmask", "high", 0.020, 9.0, denoise=True)]
    md = markdown_report(rows, recommend(rows, 0.001), tolerance=0.001, with_denoiser=recommend(rows, 0.001, denoise=None))
    plain, denoised = md.split("### With the denoiser allowed")
    assert "| s | gtao | high | no | 0.0400 |" in plain
    assert "| s | bitmask | high | yes | 0.0200 |" in denoised.split("## Error against run time")[0]
    assert "With the denoiser allowed" not in markdown_report(rows[:2], recommend(rows[:2]), tolerance=0.01,
                                                              with_denoiser=recommend(rows[:2], denoise=None))


def test_recommend_cheaper_when_tolerance_allows_best_when_not():
    rows = [_row("s", "gtao", "low", 0.080, 1.0), _row("s", "gtao", "medium", 0.050, 2.0),
            _row("s", "gtao", "high", 0.040, 4.0), _row("s", "bitmask", "high", 0.035, 8.0),
            _row("s", "bitmask", "ultra", 0.030, 20.0), _row("s", "bitmask", "ultra", 0.010, 25.0, denoise=True)]
    assert recommend(rows, 0.0)["s"]["preset"] == "ultra"  # the best itself
    rec = recommend(rows, 0.0)["s"]
    assert (rec["method"], rec["best"]["mae"]) == ("bitmask", 0.030)
    assert (recommend(rows, 0.006)["s"]["method"], recommend(rows, 0.006)["s"]["preset"]) == ("bitmask", "high")
    assert (recommend(rows, 0.011)["s"]["method"], recommend(rows, 0.011)["s"]["preset"]) == ("gtao", "high")
    assert recommend(rows, 0.021)["s"]["preset"] == "medium"
    assert recommend(rows, 1.0)["s"]["preset"] == "low"  # everything allowed: the cheapest
    assert recommend(rows, 0.0, denoise=None)["s"]["denoise"] is True
    # Per scene, and "all" on the mean of configurations present in every scene.
    rows2 = rows + [_row("t", "gtao", "low", 0.5, 1.0), _row("t", "gtao", "high", 0.1, 4.0)]
    rec = recommend(rows2, 0.01)
    assert rec["t"]["preset"] == "high" and rec["s"]["preset"] == "high"
    assert rec["all"]["method"] == "gtao" and rec["all"]["preset"] == "high"
    assert {(r["method"], r["preset"]) for r in aggregate_rows(rows2)} == {("gtao", "low"), ("gtao", "high")}
    with pytest.raises(ValueError, match="tolerance"):
        recommend(rows, -1)


def test_pareto_front():
    pts = [(1.0, 0.5), (2.0, 0.3), (3.0, 0.4), (4.0, 0.1), (0.5, 0.9), (5.0, 0.1)]
    assert pareto_front(pts) == [4, 0, 1, 3]


def test_make_method_hard_mode_and_preset():
    m = make_method(TinyAO, "high", radius=0.5)
    assert (m.slices, m.steps) == (3, 3) and float(m.radius.detach()) == 0.5
    from torch_ao.methods import get_method

    b = make_method(get_method("bitmask"), "low")
    assert b.mode == "hard"


def test_bench_cli_tiny(cache, tmp_path):
    names = ["gtao", "bitmask"]
    out = tmp_path / "bench"
    rc = main(["bench", "--methods", ",".join(names), "--presets", "low,medium", "--scenes", "sphere_on_plane",
               "--height", str(H), "--width", str(W), "--spp", str(SPP), "--repeats", "1", "--warmup", "0",
               "--cache", str(cache), "--out", str(out), "--no-progress", "--no-background", "--threads", "1"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert len(report["rows"]) == 8 and {r["method"] for r in report["rows"]} == set(names)
    assert report["environment"]["threads"] >= 1 and report["environment"]["device"] == "cpu"
    assert (out / "plot_all.png").is_file() and (out / "bench.csv").is_file()


def test_bench_cli_errors(tmp_path, capsys):
    assert main(["bench", "--presets", "low,bogus", "--out", str(tmp_path)]) == 2
    assert "--presets" in capsys.readouterr().err
    assert main(["bench", "--scenes", "nowhere", "--out", str(tmp_path)]) == 2
    assert "--scenes" in capsys.readouterr().err


def test_auto_from_report_and_errors(views, tmp_path, cache):
    from torch_ao.bench import auto_choice

    rows = [_row("sphere_on_plane", "gtao", "low", 0.08, 1.0), _row("sphere_on_plane", "gtao", "high", 0.05, 4.0),
            _row("other", "gtao", "low", 0.2, 1.0), _row("other", "gtao", "high", 0.02, 3.0)]
    for r in rows:
        r["radius"] = 0.75
    write_report(tmp_path / "rep", rows, tolerance=0.0, plots=False)
    ref = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    c = auto_choice(ref, report=tmp_path / "rep")  # file stem sphere_on_plane_32x24_... matches the scene
    assert (c["scene"], c["method"], c["preset"], c["radius"]) == ("sphere_on_plane", "gtao", "high", 0.75)
    assert auto_choice(ref, report=tmp_path / "rep", tolerance=0.05)["preset"] == "low"
    c = auto_choice(tmp_path / "elsewhere.npz", report=tmp_path / "rep/report.json")
    assert (c["scene"], c["preset"]) == ("all", "high")  # mean MAE 0.035 against 0.14
    # Neither a report nor a reference: a clear explanation.
    gb_only = tmp_path / "gb.npz"
    from torch_ao import save_npz
    save_npz(gb_only, views[0].gbuffer)
    with pytest.raises(ValueError, match="no 'ao' reference"):
        auto_choice(gb_only)
    with pytest.raises(ValueError, match="--report"):
        auto_choice(None)
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(ValueError, match="not a bench report"):
        auto_choice(ref, report=bad)


def test_auto_quick_sweep_on_reference_file(cache, monkeypatch):
    """Without a report, --auto sweeps the file's own reference (here with the tiny methods)."""
    import torch_ao.bench.auto as ba

    monkeypatch.setattr(ba, "available_methods", lambda names=None, log=None: _tiny_methods())
    ref = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    c = ba.auto_choice(ref, tolerance=0.0)
    assert c["method"] in ("tiny", "tiny_sq") and c["preset"] in ba.AUTO_PRESETS
    assert "quick sweep" in c["source"] and c["radius"] == 1.0


def test_ao_cli_auto(cache, tmp_path, capsys):
    rows = [_row("sphere_on_plane", "gtao", "low", 0.08, 1.0), _row("sphere_on_plane", "gtao", "medium", 0.05, 2.0)]
    write_report(tmp_path / "rep", rows, tolerance=0.0, plots=False)
    ref = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    rc = main(["ao", str(ref), "--auto", "--report", str(tmp_path / "rep"), "--out", str(tmp_path / "o.npz")])
    captured = capsys.readouterr()
    assert "auto: gtao preset medium" in captured.out
    assert rc == 0 and (tmp_path / "o.npz").is_file()
    assert main(["ao", "--auto", "--out", str(tmp_path / "x.npz")]) == 2
    assert "needs either a bench report" in capsys.readouterr().err


def test_default_cache_dir_rule(monkeypatch, tmp_path):
    from torch_ao.views import default_cache_dir

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("TORCH_AO_CACHE", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "torch_ao"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "torch_ao"
    monkeypatch.setenv("TORCH_AO_CACHE", "~/mine")
    assert default_cache_dir() == tmp_path / "home" / "mine"
    import torch_ao.datasets
    from torch_ao.reference.render import TRACER_VERSION

    assert torch_ao.datasets.default_cache_dir is default_cache_dir  # one rule
    assert reference_path(None, "fence", 72, 96, 64, 1.0) == tmp_path / "home" / "mine" / "references" / \
        f"fence_96x72_spp64_R1.0_seed0_v{torch_ao.__version__}-t{TRACER_VERSION}.npz"
    assert reference_path("c", "fence", 72, 96, 64, float("inf"), 3, layout=3).name == \
        f"fence_s3_96x72_spp64_Rinf_seed3_v{torch_ao.__version__}-t{TRACER_VERSION}.npz"


def test_fit_views_and_bench_views_share_the_cache(cache, views):
    """The training examples' default-layout view is the same file the bench rendered (not a second render)."""
    from torch_ao.datasets import reference_view

    path = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    mtime = path.stat().st_mtime_ns
    v = reference_view("sphere_on_plane", None, height=H, width=W, spp=SPP, max_distance=1.0, cache_dir=cache)
    assert path.stat().st_mtime_ns == mtime and len(list((cache / "references").iterdir())) == 1
    assert v.name == "sphere_on_plane/default" and torch.equal(v.reference, views[0].reference)
    assert v.max_distance == 1.0 and torch.equal(v.gbuffer.depth, views[0].gbuffer.depth)


# ------------------------------------------------------------------------------ the resolution dimension
def test_sweep_with_half_resolution_presets(views, tmp_path):
    from torch_ao.metrics import error_metrics

    rows = run_bench(views, {"tiny": TinyAO}, ["medium", "medium@half"], denoise=False, repeats=1, warmup=0,
                     progress=False, log=None)
    by = {r["preset"]: r for r in rows}
    assert set(by) == {"medium", "medium@half"}
    assert (by["medium"]["resolution"], by["medium@half"]["resolution"]) == ("full", "half")
    assert (by["medium@half"]["slices"], by["medium@half"]["steps"]) == (2, 2)
    view = views[0]
    with torch.no_grad():
        vis = make_method(TinyAO, "medium@half", radius=1.0)(view.gbuffer).visibility
    expected = error_metrics(vis, view.reference, view.gbuffer.valid)
    assert by["medium@half"]["mae"] == pytest.approx(float(expected["mae"]), rel=1e-6)
    assert by["medium@half"]["mae"] != pytest.approx(by["medium"]["mae"], rel=1e-6)  # a different walk
    files = write_report(tmp_path, rows, tolerance=0.0, env={"device": "cpu", "threads": 1})
    md = files["md"].read_text()
    table = md.split("## Error against run time")[1]
    assert "| sphere_on_plane | tiny | medium | 2x2 |" in table and "| sphere_on_plane | tiny | medium@half | 2x2 |" in table
    assert table.index("| medium |") < table.index("| medium@half |")  # full resolution first
    with open(files["csv"]) as f:
        assert {r["resolution"] for r in csv.DictReader(f)} == {"full", "half"}
    assert files["plot_sphere_on_plane"].stat().st_size > 0


def test_recommend_and_auto_pick_a_half_resolution_preset(views, tmp_path, cache, capsys):
    from torch_ao.bench import auto_choice

    rows = [_row("sphere_on_plane", "gtao", "high", 0.050, 4.0), _row("sphere_on_plane", "gtao", "high@half", 0.054, 1.2),
            _row("sphere_on_plane", "gtao", "ultra@half", 0.049, 3.5), _row("sphere_on_plane", "gtao", "low", 0.09, 1.0)]
    for r in rows:
        r["radius"] = 1.0
    assert recommend(rows, 0.005)["sphere_on_plane"]["preset"] == "high@half"
    assert recommend(rows, 0.0)["sphere_on_plane"]["preset"] == "ultra@half"  # the best, and cheaper than high
    write_report(tmp_path / "rep", rows, tolerance=0.005, plots=False)
    ref = reference_path(cache, "sphere_on_plane", H, W, SPP, 1.0)
    c = auto_choice(ref, report=tmp_path / "rep")
    assert (c["method"], c["preset"]) == ("gtao", "high@half")
    rc = main(["ao", str(ref), "--auto", "--report", str(tmp_path / "rep"), "--out", str(tmp_path / "o.npz")])
    assert rc == 0 and "auto: gtao preset high@half" in capsys.readouterr().out


def test_bench_cli_half_presets(cache, tmp_path, capsys):
    out = tmp_path / "bench"
    rc = main(["bench", "--methods", "gtao", "--presets", "low,low@half", "--scenes", "sphere_on_plane",
               "--height", str(H), "--width", str(W), "--spp", str(SPP), "--repeats", "1", "--warmup", "0",
               "--cache", str(cache), "--out", str(out), "--no-progress", "--no-background", "--no-denoise",
               "--no-backward", "--no-plots", "--threads", "1"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert [(r["preset"], r["resolution"]) for r in report["rows"]] == [("low", "full"), ("low@half", "half")]
    assert main(["bench", "--presets", "high@double", "--out", str(tmp_path)]) == 2
    assert "--presets" in capsys.readouterr().err


def test_default_sweeps_include_half_presets():
    from torch_ao.bench import AUTO_PRESETS, DEFAULT, QUICK

    for presets in (DEFAULT.presets, QUICK.presets, AUTO_PRESETS):
        assert "high@half" in presets and "high" in presets


def test_fitted_rows_keep_the_resolution_of_their_preset():
    from torch_ao.fitted import FittedPipeline, _preset_of

    assert _preset_of(FittedPipeline("gtao", {"preset": "high@half", "radius": 1.0}), "p.json") == "high@half"
    assert _preset_of(FittedPipeline("gtao", {"preset": "high", "radius": 1.0}), "p.json") == "high"
    assert _preset_of(FittedPipeline("gtao", {"slices": 9, "steps": 3, "resolution": "half"}), "p.json") == "ultra@half"


@pytest.mark.parametrize("methods", [7, 14])
def test_plot_legend_lies_inside_the_image(methods, tmp_path):
    """Every legend entry is drawn inside the saved figure (no entry cut off at the right or bottom),
    for the full method list and for twice as many curves."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from torch_ao.bench.files import error_vs_time_figure, plot_error_vs_time

    rows = [{"method": f"method_{m}", "preset": p, "denoise": d, "forward_ms": (1 + m) * (1 + i) * (1.3 if d else 1),
             "mae": 0.1 / (1 + i) + 0.01 * m, "scene": "s"}
            for m in range(methods) for i, p in enumerate(("low", "medium", "high", "ultra")) for d in (False, True)]
    fig = error_vs_time_figure(rows, title="t")
    fig.canvas.draw()
    (legend,) = fig.legends
    box, page = legend.get_window_extent(), fig.bbox
    assert len(legend.get_texts()) == 2 * methods + 1  # plain and denoised per method, and the Pareto front
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1, (box, page)
    axes = fig.axes[0].get_window_extent()
    assert axes.x1 <= box.x0 and axes.width > 0.5 * page.width  # beside the axes, which keep most of the width
    plt.close(fig)
    path = plot_error_vs_time(rows, tmp_path / "plot.png")
    assert path.stat().st_size > 0

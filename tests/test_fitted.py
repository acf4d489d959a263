"""Fitted pipelines: params.json holds everything to rebuild them (same numbers, bit for bit, as the
module that was fitted), `torch-ao ao --fitted/--denoise` and `torch-ao bench --fitted` apply them,
and the fit keeps the parameters that are best in hard mode."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from torch_ao import Denoiser, GTAO
from torch_ao.cli import main
from torch_ao.datasets import reference_view
from torch_ao.fit import FitConfig, FitView, evaluate, fit, fittable_parameters
from torch_ao.fitted import FittedPipeline, load_fitted
from torch_ao.io import read_npz, save_npz
from torch_ao.kernels import kernel_forward
from torch_ao.metrics import error_metrics
from torch_ao.methods.base import AOOutput
from torch_ao.examples import plane_gbuffer


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """Two tiny ray-traced views (fence: thin slats with object ids; stairs) and their files."""
    cache = tmp_path_factory.mktemp("refs")
    vs = [reference_view(s, 1, height=24, width=32, spp=16, max_distance=0.8, cache_dir=cache) for s in ("fence", "stairs")]
    files = [next(f for f in cache.rglob("*.npz") if f.name.startswith(s)) for s in ("fence", "stairs")]
    return vs, files


def test_pipeline_round_trip_is_exact_with_per_object_tables_and_denoiser(views, tmp_path):
    vs, _ = views
    gb = vs[0].gbuffer
    K = int(gb.object_id.max()) + 1
    pipe = FittedPipeline("bitmask", {"preset": "medium", "radius": 0.8, "weighting": "cosine",
                                      "thickness": torch.linspace(0.1, 0.9, K)}, denoiser={"kernel_size": 3})
    with torch.no_grad():  # as if fitted: values no constructor default would give
        pipe.method.thickness.mul_(1.37).add_(0.011)
        pipe.method.radius.fill_(0.7731)
    expected = pipe(gb).visibility
    path = pipe.save(tmp_path / "params.json", note="extra keys are kept")
    data = json.loads(path.read_text())
    assert data["method"] == "bitmask" and data["options"]["weighting"] == "cosine" and data["options"]["mode"] == "hard"
    assert data["parameters"]["thickness"]["shape"] == [K] and data["parameters"]["radius"] == pytest.approx(0.7731)
    assert data["denoiser"]["kernel_size"] == 3 and data["note"] == "extra keys are kept"
    assert data["torch_ao_version"] and (data["slices"], data["steps"]) == (2, 2)
    again = load_fitted(path)
    assert torch.equal(again.method.thickness, pipe.method.thickness)
    assert torch.equal(again(gb).visibility, expected)
    # the denoiser is really applied: without it the numbers differ
    assert not torch.equal(again.method(gb).visibility, expected)
    assert torch.equal(Denoiser(kernel_size=3)(again.method(gb).visibility, gb).visibility, expected)


def test_load_fitted_rebuilds_what_fit_fitted(views, tmp_path):
    vs, _ = views
    pipe = FittedPipeline("gtao", {"preset": "low", "radius": 0.8, "falloff_range": 0.25}, denoiser=True)
    assert set(fittable_parameters(pipe)) == {"radius", "falloff_range", "final_power"}
    result = fit(pipe, vs, FitConfig(params=("radius", "falloff_range", "final_power"), steps=4, lr=0.05), progress=False)
    assert result.parameters["final_power"] != 1.0  # it moved
    pipe.save(tmp_path / "p.json")
    again = load_fitted(tmp_path / "p.json")
    for v in vs:
        assert torch.equal(again(v.gbuffer).visibility, pipe(v.gbuffer).visibility)
    assert evaluate(again, vs)["mae"] == evaluate(pipe, vs)["mae"]


def test_bad_files_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="fitted: no such file"):
        load_fitted(tmp_path / "missing.json")
    (tmp_path / "a.json").write_text("{not json")
    with pytest.raises(ValueError, match="is not JSON"):
        load_fitted(tmp_path / "a.json")
    (tmp_path / "b.json").write_text(json.dumps({"method": "gtao", "options": {"colour": 1}}))
    with pytest.raises(ValueError, match="cannot rebuild 'gtao'"):
        load_fitted(tmp_path / "b.json")
    (tmp_path / "c.json").write_text(json.dumps({"method": "gtao", "format": "other/9"}))
    with pytest.raises(ValueError, match="format"):
        load_fitted(tmp_path / "c.json")
    with pytest.raises(ValueError, match="denoiser: unknown setting"):
        FittedPipeline("gtao", {}, denoiser={"radius": 2})


def test_cli_ao_fitted_and_denoise_give_the_modules_numbers(views, tmp_path):
    vs, files = views
    frame = next(f for f in files if "fence" in f.name)
    pipe = FittedPipeline("bitmask", {"preset": "low", "radius": 0.8, "thickness": 0.37, "weighting": "cosine"}, denoiser=True)
    pipe.save(tmp_path / "params.json")
    assert main(["ao", str(frame), "--fitted", str(tmp_path / "params.json"), "--out", str(tmp_path / "f.npz")]) == 0
    got = torch.from_numpy(read_npz(tmp_path / "f.npz")["visibility"]).reshape(vs[0].reference.shape)
    with torch.no_grad():  # as the CLI calls it (the kernel backend where it covers the call)
        assert torch.equal(got, pipe(vs[0].gbuffer).visibility)

    assert main(["ao", str(frame), "--method", "gtao", "--preset", "low", "--radius", "0.8", "--denoise",
                 "--out", str(tmp_path / "d.npz")]) == 0
    got = torch.from_numpy(read_npz(tmp_path / "d.npz")["visibility"]).reshape(vs[0].reference.shape)
    with torch.no_grad():
        raw = GTAO(preset="low", radius=0.8)(vs[0].gbuffer).visibility
    assert torch.equal(got, Denoiser()(raw, vs[0].gbuffer).visibility) and not torch.equal(got, raw)
    assert main(["ao", str(frame), "--fitted", str(tmp_path / "params.json"), "--preset", "high",
                 "--out", str(tmp_path / "x.npz")]) == 2
    assert not (tmp_path / "x.npz").exists()


def test_cli_bench_adds_fitted_rows(views, tmp_path):
    vs, files = views
    frame = next(f for f in files if "stairs" in f.name)
    pipe = FittedPipeline("bitmask", {"preset": "low", "radius": 0.8, "thickness": 0.2, "weighting": "cosine"}, denoiser=True)
    (tmp_path / "mine").mkdir()
    pipe.save(tmp_path / "mine" / "params.json")
    out = tmp_path / "bench"
    assert main(["bench", "--reference", str(frame), "--methods", "gtao", "--presets", "low", "--fitted",
                 str(tmp_path / "mine" / "params.json"), "--no-background", "--no-plots", "--no-backward",
                 "--repeats", "1", "--no-progress", "--out", str(out)]) == 0
    rows = json.loads((out / "report.json").read_text())["rows"]
    mine = {r["denoise"]: r for r in rows if r["method"] == "bitmask fitted (mine)"}
    assert set(mine) == {False, True} and mine[True]["preset"] == "low"
    expected = error_metrics(pipe(vs[1].gbuffer).visibility, vs[1].reference, vs[1].gbuffer.valid)
    assert mine[True]["mae"] == pytest.approx(expected["mae"], rel=1e-6)
    assert any(r["method"] == "gtao" for r in rows)


def test_cli_bench_gives_built_in_views_the_back_face_layer_a_fitted_pipeline_needs(tmp_path):
    from torch_ao.views import load_views, reference_path

    pipe = FittedPipeline("bitmask", {"preset": "low", "radius": 0.8, "thickness_model": "backface",
                                      "thickness_scale": 0.8, "thickness": 0.05}, denoiser=False)
    (tmp_path / "bf").mkdir()
    pipe.save(tmp_path / "bf" / "params.json")
    out, cache = tmp_path / "bench", tmp_path / "cache"
    assert main(["bench", "--scenes", "fence", "--width", "32", "--height", "24", "--spp", "16", "--max-distance", "0.8",
                 "--cache", str(cache), "--methods", "gtao", "--presets", "low", "--fitted", str(tmp_path / "bf" / "params.json"),
                 "--no-background", "--no-plots", "--no-backward", "--repeats", "1", "--no-progress", "--out", str(out)]) == 0
    rows = [r for r in json.loads((out / "report.json").read_text())["rows"] if r["method"] == "bitmask fitted (bf)"]
    assert rows, "the back-face pipeline was skipped"
    view = load_views([reference_path(cache, "fence", 24, 32, 16, 0.8)])[0]
    assert view.gbuffer.backface_depth is not None
    expected = error_metrics(pipe(view.gbuffer).visibility, view.reference, view.gbuffer.valid)
    assert rows[0]["mae"] == pytest.approx(expected["mae"], rel=1e-6)


def _with_radius(src, dst, radius):
    arrays = dict(np.load(src))
    arrays["max_distance"] = np.float32(radius)
    np.savez(dst, **arrays)
    return dst


def test_fit_takes_R_from_the_files_and_refuses_disagreeing_ones(views, tmp_path, capsys):
    _, files = views
    a = _with_radius(files[0], tmp_path / "a.npz", 0.8)
    b = _with_radius(files[1], tmp_path / "b.npz", 0.5)
    out = tmp_path / "out"
    assert main(["fit", "--reference", str(a), str(b), "--method", "gtao", "--preset", "low", "--steps", "2",
                 "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "disagree on max_distance" in err and "a.npz" in err and "b.npz" in err
    assert not (out / "params.json").exists()
    with pytest.warns(UserWarning, match="--radius 0.6 overrides"):
        assert main(["fit", "--reference", str(a), str(b), "--radius", "0.6", "--method", "gtao", "--preset", "low",
                     "--steps", "2", "--no-progress", "--out", str(out)]) == 0
    assert json.loads((out / "params.json").read_text())["options"]["preset"] == "low"
    # --method gtao without --params fits GTAO's own parameters; R comes from the files
    out2 = tmp_path / "out2"
    assert main(["fit", "--reference", str(a), str(files[1]), "--method", "gtao", "--preset", "low", "--steps", "3",
                 "--no-progress", "--out", str(out2)]) == 0
    data = json.loads((out2 / "params.json").read_text())
    assert data["fitted"] == ["radius", "falloff_range", "final_power"]
    assert data["denoiser"] is not None and data["history"][0]["radius"] == [pytest.approx(0.8)]
    fitted = load_fitted(out2 / "params.json")
    assert evaluate(fitted, FitView_list(files[1]))["mae"] == pytest.approx(data["after"]["mae"], rel=1e-6)


def test_fit_grows_a_thickness_growth_where_params_names_it(views, tmp_path, monkeypatch):
    """``--params ...,thickness_growth`` fits a growth from 0 (kept >= 0, the model's range, so that the params.json
    it writes loads again), every call of a walk in a kernel (the soft one with the growth's gradient)."""
    import torch_ao.methods.base as base

    _, files = views
    out = tmp_path / "out"
    on_the_tensor_path, calls = [], []

    def dispatched(module, gbuffer, backend):
        fused = kernel_forward(module, gbuffer, backend)
        calls.append(type(module).__name__)
        if fused is None:
            on_the_tensor_path.append(type(module).__name__)
        return fused

    monkeypatch.setattr(base, "kernel_forward", dispatched)
    assert main(["fit", "--reference", *map(str, files), "--params", "thickness,radius,thickness_growth", "--preset",
                 "low", "--steps", "3", "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    assert data["fitted"] == ["thickness", "radius", "thickness_growth"]
    growth = data["parameters"]["thickness_growth"]
    assert growth >= 0 and data["history"][0]["thickness_growth"] == [0.0]
    assert float(load_fitted(out / "params.json").method.thickness_growth.detach()) == pytest.approx(growth)
    assert "BitmaskAO" in calls and not on_the_tensor_path


def FitView_list(path):
    from torch_ao.fit import load_views

    return load_views([path])


class Biased(nn.Module):
    """visibility = exp(-t (depth - 3)^2 / 4) in hard mode; soft mode sees ``t - 0.5`` (a soft
    objective whose optimum is not the hard one, as soft sector masks can be)."""

    def __init__(self, t):
        super().__init__()
        self.thickness = nn.Parameter(torch.tensor(float(t)))
        self.mode, self.tau = "hard", 0.1

    def forward(self, gb):
        t = self.thickness - (0.5 if self.mode == "soft" else 0.0)
        return AOOutput(torch.exp(-t * (gb.safe_depth - 3).square() / 4))


def _biased_views():
    out = []
    for tilt in (40, 55):
        gb = plane_gbuffer(12, 16, tilt_degrees=tilt)
        with torch.no_grad():
            out.append(FitView(gb, Biased(0.3)(gb).visibility))
    return out


def _hard_loss(module, vs):
    return evaluate(module, vs)["mae"]


def test_fit_keeps_the_best_hard_mode_parameters():
    vs = _biased_views()
    soft_only = Biased(0.35)
    fit(soft_only, vs, FitConfig(steps=80, lr=0.05, hard_every=0), progress=False)
    assert soft_only.thickness.item() == pytest.approx(0.8, abs=0.05)  # the soft optimum
    hard = Biased(0.35)
    start = _hard_loss(Biased(0.35), vs)
    result = fit(hard, vs, FitConfig(steps=80, lr=0.05, hard_every=5), progress=False)
    assert _hard_loss(hard, vs) <= start
    assert _hard_loss(hard, vs) < _hard_loss(soft_only, vs) / 3
    assert [h["step"] for h in result.hard_history] == list(range(0, 80, 5)) + [80]
    best = min(result.hard_history, key=lambda h: h["loss"])
    assert result.best_step == best["step"] and hard.thickness.item() == pytest.approx(best["thickness"][0])
    assert hard.mode == "hard"
    # stopping once two hard-mode scores in a row did not improve keeps the same parameters, in fewer steps
    patient = Biased(0.35)
    early = fit(patient, vs, FitConfig(steps=80, lr=0.05, hard_every=5, hard_patience=2), progress=False)
    assert early.stopped_early and early.steps_done < 80 and early.best_step == result.best_step
    assert patient.thickness.item() == hard.thickness.item()
    assert [h["step"] for h in early.hard_history] == [h["step"] for h in result.hard_history][:len(early.hard_history)]


def test_cli_fit_main_job_tiny_keeps_hard_mode_best_and_rebuilds(tmp_path):
    """The main job at a tiny size: bitmask + denoiser with the back-face thickness model (the built-in views
    carry its layer), its radius, scale and offset by default; the kept
    parameters are never worse in hard mode on the training views than the defaults it started from,
    and params.json rebuilds the pipeline that was scored."""
    from torch_ao.datasets import train_and_holdout_views

    out, cache = tmp_path / "out", tmp_path / "cache"
    assert main(["fit", "--scenes", "fence,stairs", "--train-views", "1", "--size", "32x24", "--spp", "16",
                 "--preset", "low", "--steps", "6", "--hard-every", "2", "--hard-patience", "0", "--max-steps", "0",
                 "--holdout-scenes", "none", "--cache", str(cache), "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    assert data["fitted"] == ["radius", "thickness_scale", "thickness"] and data["denoiser"] is not None
    assert data["options"]["weighting"] == "cosine" and data["options"]["mode"] == "hard"
    assert data["options"]["thickness_model"] == "backface"
    assert [h["step"] for h in data["hard_history"]] == [0, 2, 4, 6]
    assert data["train_loss_fitted"] == min(h["loss"] for h in data["hard_history"]) <= data["train_loss_start"]
    train, held = train_and_holdout_views(["fence", "stairs"], 1, 1, height=24, width=32, spp=16, max_distance=1.0,
                                          cache_dir=cache, backface=True)
    pipeline = load_fitted(out / "params.json")
    assert evaluate(pipeline, held)["mae"] == pytest.approx(data["after"]["mae"], rel=1e-6)
    assert evaluate(pipeline, train)["mae"] == pytest.approx(data["train_loss_fitted"], rel=1e-5)
    assert set(data["per_view"]["fitted"]) == {v.name for v in held}
    report = (out / "report.md").read_text()
    assert "fence/s1000" in report and "bitmask fitted" in report


def test_cli_fit_holdout_views_and_psnr_loss(tmp_path):
    """``--holdout-views 2`` scores seeds 1000 and 1001 of every scene; ``--loss psnr`` fits (and keeps) by the
    training views' mean PSNR, which params.json's training losses are minus."""
    from torch_ao.datasets import reference_views

    out, cache = tmp_path / "out", tmp_path / "cache"
    assert main(["fit", "--scenes", "fence,stairs", "--train-views", "1", "--holdout-views", "2", "--size", "32x24",
                 "--spp", "16", "--preset", "low", "--steps", "4", "--hard-every", "2", "--loss", "psnr", "--holdout-scenes", "none", "--cache",
                 str(cache), "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    assert data["loss"] == "psnr"
    assert data["holdout_views"] == ["fence/s1000", "fence/s1001", "stairs/s1000", "stairs/s1001"]
    train = reference_views(["fence", "stairs"], [1], height=24, width=32, spp=16, max_distance=1.0, cache_dir=cache)
    pipeline = load_fitted(out / "params.json")
    assert -evaluate(pipeline, train)["psnr"] == pytest.approx(data["train_loss_fitted"], abs=1e-3)
    assert data["train_loss_fitted"] == min(h["loss"] for h in data["hard_history"]) <= data["train_loss_start"]


# ---------------------------------------------------------------- thickness models (--thickness)

@pytest.fixture(scope="module")
def backface_views(tmp_path_factory):
    """The fence and stairs views of ``views`` rendered into another cache, with the back-face layer."""
    cache = tmp_path_factory.mktemp("refs_backface")
    vs = [reference_view(s, 1, height=24, width=32, spp=16, max_distance=0.8, cache_dir=cache, backface=True)
          for s in ("fence", "stairs")]
    return vs, cache


@pytest.mark.parametrize("model, options", [
    ("linear", {"thickness": 0.05, "thickness_slope": 0.1}),
    ("backface", {"thickness_scale": 0.8, "thickness": 0.02}),
    ("object", {"thickness": torch.full((15,), 0.3)}),
])
def test_thickness_models_round_trip_after_a_fit(backface_views, tmp_path, model, options):
    """A pipeline with each thickness model, fitted a few steps: params.json names the model and its
    parameters, and load_fitted gives the fitted module's numbers bit for bit."""
    from torch_ao.fitted import THICKNESS_MODELS

    vs, _ = backface_views
    pipe = FittedPipeline("bitmask", {"preset": "low", "radius": 0.8, "weighting": "cosine", "thickness_model": model,
                                      **options}, denoiser=True)
    cls, keywords = THICKNESS_MODELS[model]
    assert type(pipe.method.thickness_model) is cls
    names = tuple(keywords)
    assert set(fittable_parameters(pipe)) == {"radius", *names}
    before = {k: v.clone() for k, v in pipe.parameter_values().items()}
    fit(pipe, vs, FitConfig(params=("radius", *names), steps=3, lr=0.05, hard_every=0), progress=False)
    moved = [k for k in names if not torch.equal(pipe.parameter_values()[k], before[k])]
    assert moved, "the fit moved none of the model's parameters"
    pipe.save(tmp_path / "params.json")
    data = json.loads((tmp_path / "params.json").read_text())
    assert data["options"]["thickness_model"] == model and set(names) <= set(data["parameters"])
    again = load_fitted(tmp_path / "params.json")
    assert type(again.method.thickness_model) is cls
    for k, v in pipe.parameter_values().items():
        assert torch.equal(again.parameter_values()[k], v), k
    for v in vs:
        assert torch.equal(again(v.gbuffer).visibility, pipe(v.gbuffer).visibility)


def test_cli_fit_chooses_the_backface_model_only_where_every_reference_holds_the_layer(backface_views, tmp_path,
                                                                                      capsys):
    """``torch-ao fit`` without ``--thickness``: ``backface`` on files that all hold ``backface_depth``; ``scalar``
    with a note naming the file when one does not; ``--thickness backface`` on that file is refused by name."""
    _, cache = backface_views
    files = sorted(Path(cache).rglob("*.npz"))
    assert len(files) == 2
    bare = tmp_path / "bare.npz"
    with np.load(files[1]) as arrays:
        np.savez(bare, **{k: arrays[k] for k in arrays.files if k != "backface_depth"})
    common = ["fit", "--preset", "low", "--steps", "1", "--max-steps", "1", "--hard-every", "1", "--no-progress"]
    assert main([*common, "--reference", str(files[0]), str(files[1]), "--out", str(tmp_path / "layer")]) == 0
    assert json.loads((tmp_path / "layer" / "params.json").read_text())["options"]["thickness_model"] == "backface"
    capsys.readouterr()
    assert main([*common, "--reference", str(files[0]), str(bare), "--out", str(tmp_path / "bare")]) == 0
    assert "note: --thickness scalar: " + str(bare) in capsys.readouterr().out
    assert "thickness_model" not in json.loads((tmp_path / "bare" / "params.json").read_text())["options"]
    assert main([*common, "--thickness", "backface", "--reference", str(files[0]), str(bare),
                 "--out", str(tmp_path / "x")]) == 2
    assert "bare.npz has no backface_depth layer" in capsys.readouterr().err


def test_backface_model_reads_the_layer_and_the_offset_only_model_is_the_scalar(backface_views):
    """thickness_scale = 0 leaves the offset: the same numbers as the scalar thickness; with scale 1
    each occluder's own thickness is used, and a G-buffer without the layer is refused."""
    vs, _ = backface_views
    gb = vs[0].gbuffer
    common = {"preset": "low", "radius": 0.8, "weighting": "cosine"}
    offset_only = FittedPipeline("bitmask", {**common, "thickness_model": "backface", "thickness_scale": 0.0,
                                             "thickness": 0.3})
    scalar = FittedPipeline("bitmask", {**common, "thickness": 0.3})
    assert torch.allclose(offset_only(gb).visibility, scalar(gb).visibility, atol=1e-6)
    own = FittedPipeline("bitmask", {**common, "thickness_model": "backface"})
    assert not torch.allclose(own(gb).visibility, scalar(gb).visibility, atol=1e-3)
    with pytest.raises(ValueError, match="backface_depth"):
        own(replace(gb, backface_depth=None))
    with pytest.raises(ValueError, match="thickness_model: expected one of scalar, object, linear, backface"):
        FittedPipeline("bitmask", {**common, "thickness_model": "quadratic"})


def test_cached_view_without_the_layer_gets_it_added_never_used_without_it(backface_views, tmp_path):
    """A cached reference rendered without --backface is extended (the same layer as a full render with
    it; every other array unchanged), and a file whose depth is not the scene's is refused."""
    from torch_ao.datasets import add_backface_layer
    from torch_ao.reference import get_scene, render_reference

    plain = reference_view("fence", 1, height=24, width=32, spp=16, max_distance=0.8, cache_dir=tmp_path)
    assert plain.gbuffer.backface_depth is None
    path = next(tmp_path.rglob("fence*.npz"))
    arrays = read_npz(path)
    view = reference_view("fence", 1, height=24, width=32, spp=16, max_distance=0.8, cache_dir=tmp_path, backface=True)
    extended = read_npz(path)
    assert set(extended) == set(arrays) | {"backface_depth"}
    for k, a in arrays.items():
        assert np.array_equal(extended[k], a), k
    full = render_reference(get_scene("fence", 1), height=24, width=32, spp=16, max_distance=0.8, seed=1,
                            uniform=False, backface=True, progress=False)
    assert torch.equal(view.gbuffer.backface_depth, full.backface_depth)
    assert torch.equal(view.reference, full.ao)
    thick = (view.gbuffer.backface_depth - view.gbuffer.depth)[view.gbuffer.valid]
    assert bool((thick >= 0).all()) and bool(torch.isinf(thick).any()) and bool(torch.isfinite(thick).any())
    assert add_backface_layer(path, "fence", 1) is False  # already there: left alone
    with pytest.raises(ValueError, match="does not hold the depth of scene 'stairs'"):
        save_npz(tmp_path / "other.npz", **arrays)
        add_backface_layer(tmp_path / "other.npz", "stairs", 1)


def test_cli_fit_thickness_models(views, backface_views, tmp_path, capsys):
    """`fit --thickness backface` refuses references without the layer (naming the file), fits the
    model's own parameters plus the radius by default, and params.json rebuilds what it scored; the
    built-in views are rendered with the layer; a method without thickness models is refused."""
    _, files = views
    assert main(["fit", "--reference", str(files[0]), "--thickness", "backface", "--preset", "low", "--steps", "2",
                 "--no-progress", "--out", str(tmp_path / "o0")]) == 2
    err = capsys.readouterr().err
    assert "--thickness backface" in err and files[0].name in err and "backface_depth" in err
    assert main(["fit", "--reference", str(files[0]), "--method", "gtao", "--thickness", "linear", "--preset", "low",
                 "--steps", "2", "--no-progress", "--out", str(tmp_path / "o1")]) == 2
    assert "gtao has no thickness model" in capsys.readouterr().err

    _, cache = backface_views
    out = tmp_path / "o2"
    assert main(["fit", "--scenes", "fence,stairs", "--train-views", "1", "--size", "32x24", "--spp", "16",
                 "--max-distance", "0.8", "--preset", "low", "--steps", "2", "--hard-every", "1", "--thickness",
                 "backface", "--holdout-scenes", "none", "--cache", str(cache), "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    assert data["fitted"] == ["radius", "thickness_scale", "thickness"]
    assert data["options"]["thickness_model"] == "backface"
    assert "backface thickness" in (out / "report.md").read_text()
    pipeline = load_fitted(out / "params.json")
    vs = [reference_view(s, 1000, height=24, width=32, spp=16, max_distance=0.8, cache_dir=cache, backface=True)
          for s in ("fence", "stairs")]
    assert evaluate(pipeline, vs)["mae"] == pytest.approx(data["after"]["mae"], rel=1e-6)

    out = tmp_path / "o3"  # the per-object table spans the ids of all the views; --fetch reaches the method
    assert main(["fit", "--reference", str(files[0]), "--thickness", "object", "--init", "0.3", "--preset", "low",
                 "--fetch", "nearest", "--steps", "1", "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    assert data["options"]["fetch"] == "nearest" and load_fitted(out / "params.json").method.fetch == "nearest"
    K = int(read_npz(files[0])["object_id"].max()) + 1
    assert data["options"]["thickness_model"] == "object" and data["parameters"]["thickness"]["shape"] == [K]
    assert data["history"][0]["thickness"] == [pytest.approx(0.3)] * K

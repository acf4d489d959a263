"""Faults while running: a checkpoint of other settings, interrupted kernel builds, interrupted and
concurrent runs, partial output, the reference cache. Tiny sizes (16x12 pixels, 16 rays per pixel)."""
from __future__ import annotations

import json
import shutil

import pytest
import torch

from torch_ao.cli import main
from torch_ao.fit import CheckpointMismatch, FitConfig, fingerprint_differences, fit, run_fingerprint

TINY = ["--size", "16x12", "--spp", "16", "--train-views", "1", "--steps", "3", "--hard-every", "2", "--no-progress"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


def _fit(capsys, cache, out, *extra, scenes="sphere_on_plane,fence"):
    code = main(["fit", *TINY, "--scenes", scenes, "--cache", str(cache), "--out", str(out), *extra])
    captured = capsys.readouterr()
    return code, captured.err


@pytest.fixture(scope="module")
def first_fit(tmp_path_factory, cache):
    """A finished fit of sphere_on_plane,fence in OUT: (OUT, its params.json text)."""
    out = tmp_path_factory.mktemp("fit") / "X"
    assert main(["fit", *TINY, "--scenes", "sphere_on_plane,fence", "--cache", str(cache), "--out", str(out)]) == 0
    return out, (out / "params.json").read_text()


def _copy(first_fit, tmp_path):
    out = tmp_path / "X"
    shutil.copytree(first_fit[0], out)
    return out


@pytest.mark.parametrize("extra, scenes, named", [
    ((), "stairs,poles", "--scenes"),
    (("--preset", "low"), "sphere_on_plane,fence", "--preset"),
    (("--method", "gtao"), "sphere_on_plane,fence", "--method"),
    (("--size", "20x12"), "sphere_on_plane,fence", "--size"),
    (("--spp", "32"), "sphere_on_plane,fence", "--spp"),
    (("--max-distance", "0.5"), "sphere_on_plane,fence", "--max-distance"),
    (("--loss", "mse"), "sphere_on_plane,fence", "--loss"),
    (("--train-views", "2"), "sphere_on_plane,fence", "--train-views"),
], ids=["scenes", "preset", "method", "size", "spp", "max-distance", "loss", "train-views"])
def test_checkpoint_of_other_settings_is_refused_by_name(first_fit, cache, tmp_path, capsys, extra, scenes, named):
    out = _copy(first_fit, tmp_path)
    code, err = _fit(capsys, cache, out, *extra, scenes=scenes)
    assert code == 2
    assert err == (f"torch-ao fit: error: --out {out}: {out / 'checkpoint.pt'} belongs to a fit with other settings "
                   f"({named}); give another --out, or --restart to discard it\n")
    assert (out / "params.json").read_text() == first_fit[1]  # nothing written


def test_restart_discards_the_checkpoint_and_fits_the_new_settings(first_fit, cache, tmp_path, capsys):
    out = _copy(first_fit, tmp_path)
    code, err = _fit(capsys, cache, out, "--restart", scenes="stairs,poles")
    assert code == 0, err
    saved = json.loads((out / "params.json").read_text())
    assert saved["train_views"] == ["stairs/s1", "poles/s1"]
    fresh = tmp_path / "fresh"
    assert _fit(capsys, cache, fresh, scenes="stairs,poles")[0] == 0
    assert json.loads((fresh / "params.json").read_text())["parameters"] == saved["parameters"]


def test_same_settings_resume_and_held_out_views_may_change(first_fit, cache, tmp_path, capsys):
    """The finished checkpoint is reused (the fit is the same) when only the scoring afterwards changes."""
    out = _copy(first_fit, tmp_path)
    code, err = _fit(capsys, cache, out, "--holdout-views", "2")
    assert code == 0, err
    saved, first = json.loads((out / "params.json").read_text()), json.loads(first_fit[1])
    assert saved["parameters"] == first["parameters"] and saved["history"] == first["history"]
    assert len(saved["holdout_views"]) == 4


def test_checkpoint_of_an_older_version_is_refused(first_fit, cache, tmp_path, capsys):
    out = _copy(first_fit, tmp_path)
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    saved["config"] = saved.pop("fingerprint")["config"]  # the earlier layout: the FitConfig fields only
    torch.save(saved, out / "checkpoint.pt")
    code, err = _fit(capsys, cache, out)
    assert code == 2 and "(another torch_ao version); give another --out, or --restart" in err


def test_changed_reference_data_is_named_when_no_setting_differs(first_fit, cache, tmp_path, capsys):
    """A cache whose files changed under the same flags: the views' digest differs."""
    out = _copy(first_fit, tmp_path)
    other_cache = tmp_path / "cache"
    shutil.copytree(cache, other_cache)
    from torch_ao.io import read_npz, save_npz

    path = other_cache / "references" / "fence_s1_16x12_spp16_R1_seed1.npz"
    arrays = read_npz(path)
    arrays["ao"] = arrays["ao"] * 0.5
    save_npz(path, **arrays)
    code, err = _fit(capsys, other_cache, out)
    assert code == 2 and "(the training views' data)" in err


def test_fingerprint_differences_most_specific_first():
    from test_fit_loop import Toy, views

    base = run_fingerprint(Toy(), views(1), FitConfig(steps=2), {"scenes": "a"})
    assert fingerprint_differences(base, run_fingerprint(Toy(), views(1), FitConfig(steps=2), {"scenes": "a"})) == []
    assert fingerprint_differences(base, run_fingerprint(Toy(), views(1), FitConfig(steps=3), {"scenes": "b"})) == ["scenes"]
    assert fingerprint_differences(base, run_fingerprint(Toy(), views(1), FitConfig(steps=3), {"scenes": "a"})) == ["steps"]
    assert fingerprint_differences(base, run_fingerprint(Toy(0.7), views(1), FitConfig(steps=2), {"scenes": "a"})) == ["module"]
    assert fingerprint_differences(base, run_fingerprint(Toy(), views(2), FitConfig(steps=2), {"scenes": "a"})) == ["views"]
    assert fingerprint_differences(None, base) == ["torch_ao_version"]


def test_library_fit_refuses_another_module_before_touching_it(tmp_path):
    from test_fit_loop import Toy, views

    ckpt = tmp_path / "c.pt"
    fit(Toy(), views(1), FitConfig(steps=2), checkpoint=ckpt, progress=False)
    other = Toy(0.9)
    with pytest.raises(CheckpointMismatch, match=r"c\.pt was written with other settings \(module\)") as info:
        fit(other, views(1), FitConfig(steps=2), checkpoint=ckpt, progress=False)
    assert info.value.differences == ("module",) and other.thickness.item() == pytest.approx(0.9)


def test_checkpoint_of_other_settings_is_refused_before_rendering(first_fit, tmp_path, capsys):
    out = _copy(first_fit, tmp_path)
    empty = tmp_path / "empty-cache"
    code, err = _fit(capsys, empty, out, scenes="stairs")
    assert code == 2 and "(--scenes)" in err
    assert not empty.exists()  # nothing rendered

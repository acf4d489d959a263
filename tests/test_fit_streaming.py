"""Fitting over views read on access (torch_ao.fit_data.ViewFiles): the same losses and result as the
views in memory, while the views in memory stay bounded by the cache (not the number of frames);
``torch-ao fit --reference`` takes folders, globs and list files, and runs data-parallel under torchrun."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torch_ao.cli import main
from torch_ao.fit import FitConfig, evaluate, fit, load_views
from torch_ao.fit_data import ViewFiles, reference_files, view_names

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_ranks import Toy, write_views  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frames")
    return folder, write_views(folder, n=12)


@pytest.mark.parametrize("cache_size", [0, 2])
def test_streamed_fit_equals_the_in_memory_fit_with_bounded_views(frames, cache_size, tmp_path):
    _, paths = frames
    cfg = FitConfig(params=("thickness", "offset"), steps=6, lr=0.05, loss="mse", hard_every=2, seed=3)
    in_memory = fit(Toy(), load_views(paths), cfg, progress=False)
    views = ViewFiles(paths, cache_size=cache_size)
    streamed = fit(Toy(), views, cfg, progress=False, checkpoint=tmp_path / "c.pt")
    assert [r["loss"] for r in streamed.history] == [r["loss"] for r in in_memory.history]  # same order, same sums
    assert [r["loss"] for r in streamed.hard_history] == [r["loss"] for r in in_memory.hard_history]
    assert streamed.parameters == in_memory.parameters and streamed.best_step == in_memory.best_step
    # 12 views: the cache plus the view in use, never more; without a cache each access reads its file
    assert views.peak_resident == cache_size + 1
    if cache_size == 0:  # fingerprint 12 + 6 steps x 12 + hard scores at 0, 2, 4, 6: 4 x 12
        assert views.reads == 12 + 6 * 12 + 4 * 12
    assert views.resident == cache_size


def test_views_in_memory_do_not_grow_with_the_number_of_frames(tmp_path):
    peaks = {}
    for n in (4, 16):
        views = ViewFiles(write_views(tmp_path / str(n), n=n), cache_size=1)
        fit(Toy(), views, FitConfig(params=("thickness",), steps=2, hard_every=1), progress=False)
        peaks[n] = views.peak_resident
    assert peaks == {4: 2, 16: 2}


def test_streamed_views_evaluate_and_slice_like_the_loaded_ones(frames):
    _, paths = frames
    views = ViewFiles(paths, cache_size=0)
    assert evaluate(Toy(0.7), views, per_view=True)["views"] == evaluate(Toy(0.7), load_views(paths), per_view=True)["views"]
    head, tail = views[:-4], views[-4:]
    assert isinstance(tail, ViewFiles) and len(head) == 8 and view_names(tail) == [str(p) for p in paths[-4:]]
    assert torch.equal(tail[0].reference, load_views([paths[8]])[0].reference)
    assert views[-1].name == str(paths[-1])
    with pytest.raises(IndexError):
        views[12]
    # evaluate read each file once, views[-1] once more (the slice counts its own); no name read a file
    assert (views.reads, tail.reads, head.reads) == (13, 1, 0)


def test_reference_files_expand_folders_globs_and_lists(frames, tmp_path):
    folder, paths = frames
    assert reference_files([folder]) == sorted(paths)
    assert reference_files([str(folder / "v1*.npz")]) == [folder / "v1.npz", folder / "v10.npz", folder / "v11.npz"]
    listing = tmp_path / "train.txt"
    listing.write_text(f"# training frames\n{paths[3]}\n\n{os.path.relpath(paths[0], tmp_path)}\n")
    listed = reference_files([listing, paths[5]])  # (the relative line is relative to the list's folder)
    assert [p.resolve() for p in listed] == [p.resolve() for p in (paths[3], paths[0], paths[5])]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="--reference: folder .*empty holds no .npz or .exr file"):
        reference_files([tmp_path / "empty"], "--reference")
    with pytest.raises(ValueError, match="no file matches"):
        reference_files([str(tmp_path / "*.exr")])
    (tmp_path / "none.txt").write_text("# nothing\n")
    with pytest.raises(ValueError, match="names no file"):
        reference_files([tmp_path / "none.txt"])


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Six tiny ray-traced frames (fence and stairs, three layouts each) in one folder."""
    from torch_ao.views import cached_reference

    cache, folder = tmp_path_factory.mktemp("cache"), tmp_path_factory.mktemp("rendered")
    for scene in ("fence", "stairs"):
        for layout in (1, 2, 3):
            path = cached_reference(scene, height=24, width=32, spp=16, max_distance=0.8, seed=layout, layout=layout,
                                    cache_dir=cache)
            shutil.copy(path, folder / f"{scene}_{layout}.npz")
    return folder


FIT = ["fit", "--method", "gtao", "--preset", "low", "--steps", "4", "--max-steps", "4", "--hard-every", "2",
       "--no-progress"]


def _params(out):
    return json.loads((out / "params.json").read_text())


@pytest.mark.slow
def test_cli_fit_on_a_folder_equals_the_files_named_one_by_one(rendered, tmp_path, capsys):
    files = sorted(rendered.glob("*.npz"))
    listing = tmp_path / "frames.txt"
    listing.write_text("\n".join(str(f) for f in files))
    got = {}
    for how, refs in {"folder": [rendered], "list": [listing], "files": files}.items():
        assert main([*FIT, "--reference", *map(str, refs), "--out", str(tmp_path / how)]) == 0
        got[how] = _params(tmp_path / how)
    assert got["folder"]["train_views"] == [str(f) for f in files[:4]]  # the last third held out
    assert got["folder"]["holdout_views"] == [str(f) for f in files[4:]]
    for how in ("list", "files"):
        assert got[how]["parameters"] == got["folder"]["parameters"]
        assert got[how]["hard_history"] == got["folder"]["hard_history"]
    assert "on 4 views, evaluating on 2 held-out views" in capsys.readouterr().out


@pytest.mark.slow
def test_cli_fit_under_torchrun_writes_one_process_result(rendered, tmp_path):
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "OMP_NUM_THREADS": "1"}
    results = {}
    for ranks in (1, 2):
        out = tmp_path / f"r{ranks}"
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}",
               "-m", "torch_ao", *FIT, "--reference", str(rendered), "--out", str(out)]
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        assert proc.stdout.count("wrote ") == 1  # only rank 0 reports
        results[ranks] = _params(out)
    one, two = results[1], results[2]
    assert two["fitted"] == one["fitted"] and two["best_step"] == one["best_step"]
    for name in one["fitted"]:
        assert two["parameters"][name] == pytest.approx(one["parameters"][name], rel=1e-5)
    assert [r["loss"] for r in two["hard_history"]] == pytest.approx([r["loss"] for r in one["hard_history"]], rel=1e-5)
    for metric in ("mae", "rmse", "psnr", "ssim"):  # held-out scores, sharded over the ranks
        assert two["after"][metric] == pytest.approx(one["after"][metric], rel=1e-5)
    assert two["per_view"]["fitted"].keys() == one["per_view"]["fitted"].keys()

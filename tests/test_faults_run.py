"""Faults while running: a checkpoint of other settings, interrupted kernel builds, interrupted and
concurrent runs, partial output, the reference cache. Tiny sizes (16x12 pixels, 16 rays per pixel)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from torch_ao.cli import main
from torch_ao.fit import CheckpointMismatch, FitConfig, fingerprint_differences, fit, run_fingerprint
from torch_ao.views import reference_path

TINY = ["--size", "16x12", "--spp", "16", "--train-views", "1", "--steps", "3", "--hard-every", "2", "--no-progress",
        "--holdout-scenes", "none"]


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

    path = reference_path(other_cache, "fence", 12, 16, 16, 1.0, 1, layout=1)
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


# ------------------------------------------------------------------------------ one line, exit 2
@pytest.fixture
def gbuffer_file(tmp_path):
    np.savez(tmp_path / "g.npz", depth=np.full((6, 8), 2.0, np.float32), fov_y_degrees=60.0)
    return tmp_path / "g.npz"


def _one_line(capsys, argv) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, (code, err)
    return err


def test_truncated_exr_is_one_line(tmp_path, capsys):
    OpenEXR = pytest.importorskip("OpenEXR")
    path = tmp_path / "t.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Z": np.full((8, 8), 2.0, np.float32)}).write(str(path))
    path.write_bytes(path.read_bytes()[:40])
    err = _one_line(capsys, ["convert", path, "--fov", "60", "--out", tmp_path / "o.npz"])
    assert f"path: {path} is not a readable OpenEXR file" in err and not (tmp_path / "o.npz").exists()


def test_gltf_perspective_camera_without_its_block_is_one_line(tmp_path, capsys):
    trimesh = pytest.importorskip("trimesh")
    from test_render_mesh import rewrite_glb_json

    src = tmp_path / "box.glb"
    trimesh.Scene(trimesh.creation.box()).export(src)

    def edit(header):
        header["cameras"] = [{"type": "perspective"}]
        header["nodes"].append({"camera": 0})
        header["scenes"][0]["nodes"].append(len(header["nodes"]) - 1)

    path = tmp_path / "cam.glb"
    rewrite_glb_json(src, path, edit)
    err = _one_line(capsys, ["render", "--mesh", path, "--width", "8", "--height", "6", "--spp", "2", "--quiet",
                             "--out", tmp_path / "o.npz"])
    assert err == (f"torch-ao render: error: mesh: {path}: cameras[0].perspective.yfov: a perspective camera needs "
                   "its 'perspective' block with 'yfov'\n")


def test_deeply_nested_params_json_is_one_line(gbuffer_file, tmp_path, capsys):
    deep = tmp_path / "params.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    err = _one_line(capsys, ["ao", gbuffer_file, "--fitted", deep, "--out", tmp_path / "o.npz"])
    assert err == f"torch-ao ao: error: fitted: {deep} is nested too deeply to be a params.json\n"


def test_params_json_radius_zero_is_refused_like_the_flag(gbuffer_file, tmp_path, capsys):
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"method": "gtao", "options": {"preset": "low"}, "parameters": {"radius": 0.0}}))
    err = _one_line(capsys, ["ao", gbuffer_file, "--fitted", params, "--out", tmp_path / "o.npz"])
    assert "cannot rebuild 'gtao' (radius: expected a number > 0.0, got 0.0)" in err
    assert "radius: expected a number > 0" in _one_line(capsys, ["ao", gbuffer_file, "--radius", "0", "--out", tmp_path / "o.npz"])
    assert not (tmp_path / "o.npz").exists()


@pytest.mark.parametrize("command", ["ao", "render", "fit", "bench"])
def test_out_that_is_a_folder_is_refused_before_computing(gbuffer_file, tmp_path, capsys, command):
    folder = tmp_path / "taken.npz"
    folder.mkdir()
    argv = {"ao": ["ao", gbuffer_file], "render": ["render", "sphere_on_plane"], "fit": ["fit"], "bench": ["bench"]}[command]
    if command in ("fit", "bench"):
        folder = tmp_path / "file"
        folder.write_text("")
    err = _one_line(capsys, [*argv, "--out", folder])
    expected = f"{folder} is a file; expected a folder" if command in ("fit", "bench") else \
        f"{folder} is a folder; expected a file name"
    assert err == f"torch-ao {command}: error: --out: {expected}\n"


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
@pytest.mark.parametrize("command", ["render", "fit", "ao", "bench"])
def test_cuda_device_without_cuda_is_one_line(tmp_path, capsys, command):
    argv = {"render": ["render", "sphere_on_plane", "--out", tmp_path / "o.npz"], "fit": ["fit", "--out", tmp_path / "f"],
            "ao": ["ao", "--out", tmp_path / "o.npz"], "bench": ["bench", "--out", tmp_path / "b"]}[command]
    err = _one_line(capsys, [*argv, "--device", "cuda"])
    assert err == f"torch-ao {command}: error: --device: CUDA is not available on this machine\n"
    assert list(tmp_path.iterdir()) == []


def test_malformed_device_is_one_line(tmp_path, capsys):
    err = _one_line(capsys, ["render", "sphere_on_plane", "--out", tmp_path / "o.npz", "--device", "gpu7"])
    assert err == "torch-ao render: error: --device: expected a torch device such as cpu, cuda or cuda:1, got 'gpu7'\n"


def test_png_decompression_bomb_is_one_line(tmp_path, capsys):
    pytest.importorskip("PIL")
    import struct
    import zlib

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    bomb = tmp_path / "bomb.png"  # a 30000 x 30000 16-bit header over a few bytes of data
    bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 30000, 30000, 16, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b""))
    err = _one_line(capsys, ["convert", bomb, "--fov", "60", "--out", tmp_path / "o.npz"])
    # refused from its header, before anything is inflated, with the limit and how to raise it
    assert err == (f"torch-ao convert: error: path: {bomb} (30000x30000 PNG): needs 900,000,000 pixels, above the "
                   "limit of 268,435,456 pixels (TORCH_AO_MAX_IMAGE_PIXELS raises it)\n")


@pytest.mark.parametrize("error, message", [
    (MemoryError(), "out of memory (MemoryError); use a smaller size, fewer samples or another --device"),
    (RuntimeError("[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: can't allocate memory: you tried "
                  "to allocate 1099511627776 bytes."), "out of memory ([enforce fail at alloc_cpu.cpp:117] data. "
     "DefaultCPUAllocator: can't allocate memory: you tried to allocate 1099511627776 bytes.); use a smaller size"),
    (RecursionError("maximum recursion depth exceeded"), "the input is nested too deeply to read"),
    (PermissionError(13, "Permission denied", "/x/g.npz"), "/x/g.npz: Permission denied"),
])
def test_machine_errors_are_one_line(gbuffer_file, tmp_path, capsys, monkeypatch, error, message):
    import torch_ao.commands.ao as ao

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(ao, "load_gbuffer", fail)
    err = _one_line(capsys, ["ao", gbuffer_file, "--out", tmp_path / "o.npz"])
    assert err.startswith(f"torch-ao ao: error: {message}")


@pytest.mark.parametrize("bug", [KeyError("x"), RuntimeError("boom"), AttributeError("no")])
def test_genuine_bugs_keep_their_traceback(gbuffer_file, tmp_path, monkeypatch, bug):
    import torch_ao.commands.ao as ao

    def fail(*args, **kwargs):
        raise bug

    monkeypatch.setattr(ao, "load_gbuffer", fail)
    with pytest.raises(type(bug)):
        main(["ao", str(gbuffer_file), "--out", str(tmp_path / "o.npz")])


def test_debug_environment_keeps_the_traceback_of_user_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_AO_DEBUG", "1")
    with pytest.raises(FileNotFoundError, match="no such file"):
        main(["ao", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "o.npz")])


def test_exr_without_camera_names_flags_that_ao_takes(tmp_path, capsys):
    OpenEXR = pytest.importorskip("OpenEXR")
    path = tmp_path / "x.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Z": np.full((8, 8), 2.0, np.float32)}).write(str(path))
    err = _one_line(capsys, ["ao", path, "--out", tmp_path / "o.npz"])
    assert err == "torch-ao ao: error: camera: x.exr names no camera; give --fov DEGREES or --intrinsics FX,FY,CX,CY\n"
    # the flags it names are ao's own (the input flags every reading command shares), and convert's
    assert main(["ao", str(path), "--fov", "60", "--out", str(tmp_path / "o.npz")]) == 0
    assert main(["convert", str(path), "--fov", "60", "--out", str(tmp_path / "c.npz")]) == 0


# ------------------------------------------------------------------------------ no partial output
@pytest.mark.parametrize("flags, message", [
    (["--png", "bad.txt"], "--png: expected a .png file name, got '{d}/bad.txt'"),
    (["--out", "{d}/x.txt"], "--out: expected a .npz file name, got '{d}/x.txt'"),
    (["--out", "{d}/file/x.npz"], "--out: cannot write {d}/file/x.npz: {d}/file is not a folder"),
], ids=["png", "out-suffix", "out-parent"])
def test_bad_output_paths_are_refused_before_anything_is_written(gbuffer_file, tmp_path, capsys, flags, message):
    (tmp_path / "file").write_text("")
    flags = [f.format(d=tmp_path) if "{d}" in f else str(tmp_path / f) if f.endswith(".txt") else f for f in flags]
    argv = ["ao", gbuffer_file, "--out", tmp_path / "x.npz", *flags]
    before = sorted(tmp_path.iterdir())
    err = _one_line(capsys, argv)
    assert err == f"torch-ao ao: error: {message.format(d=tmp_path)}\n"
    assert sorted(tmp_path.iterdir()) == before


def test_save_png_is_atomic(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from torch_ao import images

    path = tmp_path / "v.png"
    images.save_png(path, torch.zeros(1, 1, 4, 4))
    first = path.read_bytes()
    plt = images.pyplot()

    def half_written(target, *args, **kwargs):
        open(target, "wb").write(b"\x89PNG partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(plt, "imsave", half_written)
    with pytest.raises(KeyboardInterrupt):
        images.save_png(path, torch.ones(1, 1, 4, 4))
    assert path.read_bytes() == first and sorted(p.name for p in tmp_path.iterdir()) == ["v.png"]


# ------------------------------------------------------------------------------ the reference cache
def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_cache_key_holds_r_exactly_and_the_versions(tmp_path):
    import torch_ao
    from torch_ao.reference.render import TRACER_VERSION

    a, b = (reference_path(tmp_path, "fence", 12, 16, 16, r) for r in (0.5, 0.5000001))
    assert a != b and a.name == f"fence_16x12_spp16_R0.5_seed0_v{torch_ao.__version__}-t{TRACER_VERSION}.npz"
    assert "R0.5000001_" in b.name


def test_a_cached_file_of_another_request_is_rendered_again(tmp_path):
    from torch_ao.io import read_npz
    from torch_ao.views import cached_reference

    low = cached_reference("sphere_on_plane", height=12, width=16, spp=16, max_distance=1.0, cache_dir=tmp_path)
    planted = reference_path(tmp_path, "sphere_on_plane", 12, 16, 64, 1.0)
    shutil.copy(low, planted)  # a spp-16 file under the spp-64 name
    got = cached_reference("sphere_on_plane", height=12, width=16, spp=64, max_distance=1.0, cache_dir=tmp_path)
    assert got == planted and int(read_npz(got)["spp"]) == 64
    assert not np.array_equal(read_npz(got)["ao"], read_npz(low)["ao"])
    before = got.stat().st_mtime_ns
    cached_reference("sphere_on_plane", height=12, width=16, spp=64, max_distance=1.0, cache_dir=tmp_path)
    assert got.stat().st_mtime_ns == before  # a matching file is used as it is


def test_a_concurrent_runs_cached_file_with_more_layers_stands(tmp_path, monkeypatch):
    """Two runs render the same missing reference; the first publishes it and adds its back-face layer while
    the second still renders: the second keeps the first's file (it used to overwrite it without the layer,
    and the first then read a reference without back faces: tests/test_faults_run.py's concurrent fits)."""
    import torch_ao.reference as reference
    from torch_ao.io import read_npz
    from torch_ao.views import add_backface_layer, cached_reference

    render = reference.render_reference
    path = reference_path(tmp_path, "sphere_on_plane", 12, 16, 16, 1.0)

    def rendered_while_another_run_publishes(*args, **kwargs):
        result = render(*args, **kwargs)
        monkeypatch.setattr(reference, "render_reference", render)  # (the other run renders as it should)
        cached_reference("sphere_on_plane", height=12, width=16, spp=16, max_distance=1.0, cache_dir=tmp_path)
        assert add_backface_layer(path, "sphere_on_plane", None)
        return result

    monkeypatch.setattr(reference, "render_reference", rendered_while_another_run_publishes)
    got = cached_reference("sphere_on_plane", height=12, width=16, spp=16, max_distance=1.0, cache_dir=tmp_path)
    assert got == path and "backface_depth" in read_npz(path)


def test_a_write_that_keeps_an_existing_file(tmp_path):
    from torch_ao.io import npz as io

    path = tmp_path / "x.txt"
    io.write_atomic(path, lambda tmp: open(tmp, "w").write("first"), keep_existing=True)
    io.write_atomic(path, lambda tmp: open(tmp, "w").write("second"), keep_existing=True)
    assert path.read_text() == "first" and [p.name for p in tmp_path.iterdir()] == ["x.txt"]
    io.write_atomic(path, lambda tmp: open(tmp, "w").write("third"))
    assert path.read_text() == "third"


def test_only_dead_or_old_writers_temporaries_are_removed(tmp_path):
    import os
    import time

    from torch_ao.io import npz as io

    host, dead = io._HOST, _dead_pid()
    names = {"dead": f"x.npz.{host}-{dead}.abcd1234.tmp.npz", "live": f"x.npz.{host}-{os.getpid()}.abcd1234.tmp.npz",
             "other-host": f"x.npz.elsewhere-{dead}.abcd1234.tmp.npz", "unnamed-fresh": "x.npz.abcd1234.tmp.npz",
             "unnamed-old": "y.npz.abcd1234.tmp.npz", "live-but-old": f"z.pt.{host}-{os.getpid()}.abcd1234.tmp"}
    for name in names.values():
        (tmp_path / name).write_bytes(b"partial")
    old = time.time() - io.STALE_TEMPORARY_SECONDS - 60
    for key in ("unnamed-old", "live-but-old"):
        os.utime(tmp_path / names[key], (old, old))
    removed = {p.name for p in io.remove_stale_temporaries(tmp_path)}
    assert removed == {names[k] for k in ("dead", "unnamed-old", "live-but-old")}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[k] for k in ("live", "other-host", "unnamed-fresh"))


def test_cache_writes_and_checkpoints_clean_dead_writers_leftovers_only(tmp_path):
    import os

    from torch_ao.io import npz as io
    from torch_ao.fit import remove_stale_temporaries
    from torch_ao.views import cached_reference

    refs = tmp_path / "references"
    refs.mkdir()
    dead = refs / f"other.npz.{io._HOST}-{_dead_pid()}.abcd1234.tmp.npz"
    live = refs / f"other.npz.{io._HOST}-{os.getpid()}.abcd1234.tmp.npz"
    dead.write_bytes(b"partial")
    live.write_bytes(b"in progress")
    cached_reference("sphere_on_plane", height=12, width=16, spp=16, max_distance=1.0, cache_dir=tmp_path)
    assert not dead.exists() and live.exists()
    ckpt = tmp_path / "checkpoint.pt"
    in_progress = tmp_path / f"checkpoint.pt.{io._HOST}-{os.getpid()}.abcd1234.tmp"
    in_progress.write_bytes(b"a concurrent run's checkpoint being written")
    remove_stale_temporaries(ckpt)
    assert in_progress.exists()


# ------------------------------------------------------------------------------ interrupted at every phase
FIT = ["fit", *TINY, "--scenes", "sphere_on_plane,fence"]
TIMED = ("seconds", "fit_seconds")


def _untimed(x):
    """``x`` without its timings (what differs between two runs of the same fit)."""
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if k not in TIMED}
    return [_untimed(v) for v in x] if isinstance(x, list) else x


def _fit_outputs(out):
    return _untimed(json.loads((out / "params.json").read_text())), (out / "comparison.png").read_bytes()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """A fit from an empty cache: its outputs, and the number of forward passes of the pipeline it made."""
    from torch_ao.fitted import FittedPipeline

    root = tmp_path_factory.mktemp("straight")
    calls = [0]
    forward = FittedPipeline.forward

    def counting(self, *args, **kwargs):
        calls[0] += 1
        return forward(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(FittedPipeline, "forward", counting)
        assert main([*FIT, "--cache", str(root / "cache"), "--out", str(root / "out")]) == 0
    return _fit_outputs(root / "out"), calls[0]


def _interrupt_at(monkeypatch, owner, name, n, *, partial=None):
    """Make the ``n``-th call of ``owner.name`` raise ``KeyboardInterrupt`` (as Ctrl-C there would), after
    ``partial(*args)`` when given (a write cut short)."""
    original, calls = getattr(owner, name), [0]

    def wrapper(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n:
            if partial is not None:
                partial(*args)
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)


def _half_written(target, *args, **kwargs):
    with open(target, "wb") as f:
        f.write(b"PK\x03\x04 cut short")


PHASES = {
    "rendering the 2nd reference": ("render_reference", 2),
    "writing the 3rd reference": ("savez", 3),
    "the first hard-mode score": ("forward", 1),
    "a soft step": ("forward", 0.25),
    "scoring the held-out views": ("forward", 0.8),
    "the last forward pass": ("forward", 1.0),
    "writing report.md": ("replace", -3),
    "writing params.json": ("replace", -2),
    "writing comparison.png": ("replace", -1),
}


@pytest.mark.parametrize("phase", list(PHASES))
def test_fit_interrupted_at_each_phase_then_rerun_gives_the_same_result(uninterrupted, tmp_path, monkeypatch, capsys, phase):
    import os

    import torch_ao.reference as reference
    from torch_ao.fitted import FittedPipeline

    (expected, forwards), (what, n) = uninterrupted, PHASES[phase]
    cache, out = tmp_path / "cache", tmp_path / "out"
    argv = [*FIT, "--cache", str(cache), "--out", str(out)]
    if what == "render_reference":
        _interrupt_at(monkeypatch, reference, "render_reference", n)
    elif what == "savez":
        _interrupt_at(monkeypatch, np, "savez_compressed", n, partial=_half_written)
    elif what == "forward":
        _interrupt_at(monkeypatch, FittedPipeline, "forward", max(1, round(n * forwards)))
    else:  # the n-th rename from the end: the outputs are written last (report.md, params.json, comparison.png)
        main(argv[:-2] + ["--out", str(tmp_path / "count")])  # (renders the cache too)
        replaces = [0]
        real = os.replace
        monkeypatch.setattr(os, "replace", lambda *a: replaces.__setitem__(0, replaces[0] + 1) or real(*a))
        main(argv[:-2] + ["--out", str(tmp_path / "count2")])
        monkeypatch.setattr(os, "replace", real)
        _interrupt_at(monkeypatch, os, "replace", replaces[0] + 1 + n)
    capsys.readouterr()
    assert main(argv) == 130
    assert "interrupted" in capsys.readouterr().err
    monkeypatch.undo()
    assert main(argv) == 0
    assert _fit_outputs(out) == expected
    leftovers = [p for p in [*out.iterdir(), *(cache / "references").iterdir()] if ".tmp" in p.name]
    assert leftovers == []


@pytest.mark.parametrize("phase", ["tracing", "writing the .npz", "writing the .png"])
def test_render_interrupted_then_rerun_gives_the_same_file(tmp_path, monkeypatch, capsys, phase):
    import os

    import torch_ao.commands.render as render

    argv = ["render", "fence", "--width", "16", "--height", "12", "--spp", "16", "--quiet"]
    assert main([*argv, "--out", str(tmp_path / "a.npz"), "--png", str(tmp_path / "a.png")]) == 0
    out, png = tmp_path / "b" / "b.npz", tmp_path / "b" / "b.png"
    if phase == "tracing":
        import torch_ao.reference as reference

        monkeypatch.setattr(reference, "render_reference", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    elif phase == "writing the .npz":
        _interrupt_at(monkeypatch, np, "savez_compressed", 1, partial=_half_written)
    else:
        _interrupt_at(monkeypatch, render, "write_png", 1)
    assert main([*argv, "--out", str(out), "--png", str(png)]) == 130
    assert not out.exists() or phase == "writing the .png"
    monkeypatch.undo()
    capsys.readouterr()
    assert main([*argv, "--out", str(out), "--png", str(png)]) == 0
    from torch_ao.io import read_npz

    a, b = read_npz(tmp_path / "a.npz"), read_npz(out)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert png.read_bytes() == (tmp_path / "a.png").read_bytes()
    assert sorted(os.listdir(out.parent)) == ["b.npz", "b.png"]


# ------------------------------------------------------------------------------ real kills, concurrent runs
def _cli(*argv, **kwargs):
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "torch_ao.cli", *map(str, argv)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize("when", ["a reference is cached", "the checkpoint exists", "params.json exists"])
def test_fit_killed_with_sigkill_then_rerun_gives_the_same_result(uninterrupted, tmp_path, when):
    import signal
    import time

    cache, out = tmp_path / "cache", tmp_path / "out"
    argv = [*FIT, "--cache", cache, "--out", out]
    sign = {"a reference is cached": lambda: any((cache / "references").glob("*.npz")) if (cache / "references").is_dir() else False,
            "the checkpoint exists": lambda: (out / "checkpoint.pt").exists(),
            "params.json exists": lambda: (out / "params.json").exists()}[when]
    proc = _cli(*argv)
    deadline = time.time() + 120
    while not sign() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    rerun = _cli(*argv)
    stdout, stderr = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, stderr
    assert _fit_outputs(out) == uninterrupted[0]


@pytest.mark.slow
def test_two_concurrent_fits_share_a_cache(uninterrupted, tmp_path):
    cache = tmp_path / "cache"
    runs = [_cli(*FIT, "--cache", cache, "--out", tmp_path / f"out{i}") for i in range(2)]
    for run in runs:
        _, stderr = run.communicate(timeout=300)
        assert run.returncode == 0, stderr
    for i in range(2):
        assert _fit_outputs(tmp_path / f"out{i}") == uninterrupted[0]
    assert [p.name for p in (cache / "references").iterdir() if ".tmp" in p.name] == []

"""Conventions that cannot go silently wrong: each common mistake reading an engine's G-buffer either
gives the right AO or one error line naming the flag that fixes it."""
import argparse
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_ao.cli import build_parser, main
from torch_ao.io.engine import ENGINE_OPTIONS


def _input_flags(command: str) -> dict[str, str]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    parser = sub.choices[command]
    return {a.option_strings[0]: a.help for a in parser._actions
            if a.dest in {o.name for o in ENGINE_OPTIONS} and a.help is not argparse.SUPPRESS}


def test_every_command_reading_gbuffers_has_the_same_input_flags():
    flags = {c: _input_flags(c) for c in ("ao", "bench", "fit", "convert")}
    assert set(flags["ao"]) == {"--" + o.name.replace("_", "-") for o in ENGINE_OPTIONS}
    for command in ("bench", "fit", "convert"):
        assert flags[command] == flags["ao"], command


@pytest.mark.parametrize("argv, message", [
    (["ao", "--far", "10"], "torch-ao ao: error: --far: applies to a GBUFFER file, and none was given"),
    (["fit", "--normal-space", "world"], "torch-ao fit: error: --normal-space: applies to --reference files, and none was given"),
    (["bench", "--fov", "60"], "torch-ao bench: error: --fov: applies to --reference files, and none was given"),
    (["ao", "x.npz", "--fov", "60", "--intrinsics", "1,1,0,0"], "torch-ao ao: error: --fov: give fov or intrinsics, not both"),
])
def test_input_flags_without_files_or_contradicting_are_refused(argv, message, capsys, tmp_path):
    assert main(argv + ["--out", str(tmp_path / "o.npz")]) == 2
    assert capsys.readouterr().err.strip() == message
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------- shared fixtures
from torch_ao import GBuffer, gtao, load_gbuffer  # noqa: E402
from torch_ao.examples import example_gbuffer  # noqa: E402
from torch_ao.io import read_npz  # noqa: E402

H, W = 36, 64
FOV = 60.0


def _frame() -> GBuffer:
    """A floor meeting a wall (exact planes, 60 degree vertical field of view, 64x36) with a background corner."""
    gb = example_gbuffer(H, W)
    depth = gb.depth.clone()
    depth[..., :3, :4] = float("inf")
    return GBuffer(depth, gb.camera, normals=gb.normals)


def _arrays(gb: GBuffer) -> dict:
    return {"depth": gb.depth[0, 0].numpy().astype(np.float64), "normal": gb.normals[0].permute(1, 2, 0).numpy(),
            "fov_y_degrees": np.float32(FOV)}


def _ao(gb: GBuffer) -> torch.Tensor:
    return gtao(gb, preset="low", radius=1.0, jitter=False).visibility


def _write(path, arrays: dict):
    np.savez(path, **arrays)
    return path


# ------------------------------------------------------------------------------------ device depth
def _encode(z: np.ndarray, encoding: str, near: float, far: float) -> np.ndarray:
    """Hardware depth of view-axis depth ``z`` (float64 formula, stored as float32): reverse-z
    ``near (far - z) / (z (far - near))`` (``near / z`` for an infinite far), device ``1 -`` that."""
    with np.errstate(invalid="ignore"):
        d = near / z if np.isinf(far) else near * (far - z) / (z * (far - near))
    d = np.where(np.isfinite(z), d, 0.0)
    return (d if encoding == "reverse-z" else 1.0 - d).astype(np.float32)


@pytest.mark.parametrize("encoding, near, far", [("device", 0.5, 100.0), ("reverse-z", 0.1, 1000.0),
                                                 ("reverse-z", 0.1, float("inf"))])
def test_device_and_reverse_z_depth_match_linear_depth(encoding, near, far, tmp_path):
    gb = _frame()
    arrays = _arrays(gb)
    arrays["depth"] = _encode(arrays["depth"], encoding, near, far)
    got, _ = load_gbuffer(_write(tmp_path / "d.npz", arrays), depth_encoding=encoding, near=near, far=far)
    assert torch.equal(got.valid, gb.valid)  # the far plane (the cleared value) is background
    v = gb.valid
    assert torch.allclose(got.depth[v], gb.depth[v], rtol=2e-5, atol=0)  # float32 storage of d
    assert (_ao(got) - _ao(gb)).abs().max() < 1e-4


def test_device_depth_cli_and_refusals(tmp_path, capsys):
    gb = _frame()
    arrays = _arrays(gb)
    arrays["depth"] = _encode(arrays["depth"], "reverse-z", 0.1, float("inf"))
    path = _write(tmp_path / "d.npz", arrays)
    out = tmp_path / "out.npz"
    assert main(["convert", str(path), "--depth-encoding", "reverse-z", "--near", "0.1", "--far", "inf", "--out", str(out)]) == 0
    depth = read_npz(out)["depth"][0]
    ok = gb.valid[0, 0].numpy()
    assert np.allclose(depth[ok], gb.depth[0, 0].numpy()[ok], rtol=2e-5) and np.isinf(depth[~ok]).all()
    capsys.readouterr()
    for argv, message in [
        (["--depth-encoding", "reverse-z"], "--depth-encoding: reverse-z depth needs the projection's near and far planes: "
                                            "give --near and --far (--far inf for an infinite far plane)"),
        (["--depth-encoding", "device", "--near", "1", "--far", "0.5"], "--far: expected a far plane beyond near=1, got 0.5"),
        (["--near", "0.1"], "--near: only for --depth-encoding device or reverse-z"),
    ]:
        assert main(["ao", str(path), *argv, "--out", str(tmp_path / "ao.npz")]) == 2
        assert capsys.readouterr().err.strip() == f"torch-ao ao: error: {message}"
    linear = _arrays(gb)
    linear["depth"] = linear["depth"] + 10.0  # linear depth is not in [0, 1]
    assert main(["ao", str(_write(tmp_path / "l.npz", linear)), "--depth-encoding", "device", "--near", "0.1",
                 "--far", "100", "--out", str(tmp_path / "ao.npz")]) == 2
    assert "--depth-encoding: device depth lies in [0, 1], got values in [" in capsys.readouterr().err
    assert not (tmp_path / "ao.npz").exists()


# ------------------------------------------------------------------------------------- view matrix
def test_row_vector_view_matrix_is_refused_suggesting_the_transpose(tmp_path, capsys):
    gb = _frame()
    M = np.array([[0.0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, -2], [0, 0, 0, 1]])  # world -> view
    arrays = _arrays(gb)
    arrays["normal"] = (arrays["normal"].astype(np.float64) @ M[:3, :3]).astype(np.float32)  # world normals
    path = _write(tmp_path / "w.npz", arrays)
    flags = ["--normal-space", "world", "--out", str(tmp_path / "o.npz")]
    fmatrix = ",".join(f"{x:g}" for x in M.T.reshape(-1))  # Unreal's FMatrix: row vectors, translation in the last row
    assert main(["convert", str(path), f"--view-matrix={fmatrix}", *flags]) == 2
    assert capsys.readouterr().err.strip() == (
        "torch-ao convert: error: --view-matrix: expected a bottom row (0, 0, 0, 1) (p_view = M @ (p_world, 1)), "
        "got (0, 0, -2, 1): it is a row-vector matrix (such as Unreal's FMatrix); give its transpose")
    assert not (tmp_path / "o.npz").exists()
    assert main(["convert", str(path), "--view-matrix=" + ",".join(f"{x:g}" for x in M.reshape(-1)), *flags]) == 0
    n = read_npz(tmp_path / "o.npz")["normal"][0]
    ok = gb.valid[0, 0].numpy()
    assert np.allclose(n[ok], _arrays(gb)["normal"][ok], atol=1e-6)


# ------------------------------------------------------------------------------- engine EXR mistakes
def _exr(path, channels: dict):
    OpenEXR = pytest.importorskip("OpenEXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}).write(str(path))
    return path


def _vector(prefix: str, x: np.ndarray, letters="XYZ") -> dict:
    return {f"{prefix}.{c}": x[..., i] for i, c in enumerate(letters)}


M = np.array([[0.0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, -2], [0, 0, 0, 1]])  # world -> view
M_FLAG = "--view-matrix=" + ",".join(f"{x:g}" for x in M.reshape(-1))


def test_blender_channel_names_mean_world_space_normals(tmp_path, capsys):
    gb = _frame()
    a = _arrays(gb)
    depth = np.where(np.isfinite(a["depth"]), a["depth"], 1e10)
    world = a["normal"].astype(np.float64) @ M[:3, :3]
    path = _exr(tmp_path / "blender.exr", {"ViewLayer.Depth.Z": depth, **_vector("ViewLayer.Normal", world)})
    out = tmp_path / "o.npz"
    assert main(["convert", str(path), "--fov", "60", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == (
        "torch-ao convert: error: --normal-space: ViewLayer.Normal is Blender's Normal pass, in world space: give "
        "--view-matrix (the camera's world-to-view matrix), or --normal-space view if it holds view-space vectors")
    assert not out.exists()
    assert main(["ao", str(path), "--fov", "60", M_FLAG, "--method", "gtao", "--preset", "low", "--radius", "1",
                 "--no-jitter", "--out", str(out)]) == 0  # world space without --normal-space world
    got = read_npz(out)
    ok = gb.valid[0, 0].numpy()
    assert np.allclose(got["normal"][0][ok], a["normal"][ok], atol=1e-6)
    assert np.abs(got["visibility"][0] - _ao(gb)[0, 0].numpy()).max() < 1e-5
    # a plain "Normal" layer without Blender's LAYER.Depth.Z stays view space
    plain = _exr(tmp_path / "plain.exr", {"Z": depth, **_vector("Normal", a["normal"])})
    assert main(["convert", str(plain), "--fov", "60", "--out", str(out)]) == 0
    assert np.allclose(read_npz(out)["normal"][0][ok], a["normal"][ok], atol=1e-6)


def test_normals_stored_as_unorm_are_detected_and_decoded(tmp_path, capsys):
    gb = _frame()
    a = _arrays(gb)
    encoded = dict(a, normal=(0.5 * a["normal"] + 0.5).astype(np.float32))
    path = _exr(tmp_path / "n.exr", {"Z": a["depth"], **_vector("N", encoded["normal"])})
    out = tmp_path / "ao.npz"
    argv = ["ao", str(path), "--fov", "60", "--method", "gtao", "--preset", "low", "--radius", "1", "--no-jitter",
            "--out", str(out)]
    with pytest.warns(UserWarning, match=r"^normal_encoding: the normals are stored as 0\.5 n \+ 0\.5") as record:
        assert main(argv) == 0
    assert sum("normal_encoding" in str(w.message) for w in record) == 1
    assert np.abs(read_npz(out)["visibility"][0] - _ao(gb)[0, 0].numpy()).max() < 1e-5
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # said: no warning
        assert main(argv + ["--normal-encoding", "unorm"]) == 0
        assert np.abs(read_npz(out)["visibility"][0] - _ao(gb)[0, 0].numpy()).max() < 1e-5
        # signed unit normals whose components happen to be in [0, 1] are not touched
        assert main(["convert", str(_exr(tmp_path / "s.exr", {"Z": a["depth"], **_vector("N", np.abs(a["normal"]))})),
                     "--fov", "60", "--out", str(tmp_path / "s.npz")]) == 0


def test_unreal_sky_without_far_names_far(tmp_path, capsys):
    gb = _frame()
    a = _arrays(gb)
    sky = ~np.isfinite(a["depth"])
    depth = np.where(sky, 65504.0, a["depth"])
    normal = np.where(sky[..., None], 0.0, a["normal"])
    path = _exr(tmp_path / "unreal.exr", {"SceneDepth.R": depth, **_vector("WorldNormal", normal, "RGB")})
    out = tmp_path / "ao.npz"
    assert main(["ao", str(path), "--fov", "60", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == (
        "torch-ao ao: error: --far: 12 valid pixels have zero-length normals, all at depth >= 65504 (beyond every "
        "other pixel: a far plane or sky); give --far 65504 to make them background")
    assert main(["ao", str(path), "--fov", "60", "--far", "65504", "--method", "gtao", "--preset", "low", "--radius",
                 "1", "--no-jitter", "--out", str(out)]) == 0
    assert np.abs(read_npz(out)["visibility"][0] - _ao(gb)[0, 0].numpy()).max() < 1e-5


def test_a_horizontal_fov_gets_a_warning(tmp_path, capsys):
    """The rule: with normals in the file, warn when the median angle between them and the normals
    reconstructed from depth is over 2 degrees with --fov read as vertical and under a quarter of that
    read as horizontal."""
    gb = _frame()
    a = _arrays(gb)
    del a["fov_y_degrees"]
    horizontal = np.degrees(2 * np.arctan(np.tan(np.radians(FOV) / 2) * W / H))  # what Blender displays
    path = _write(tmp_path / "f.npz", a)
    out = tmp_path / "o.npz"
    argv = ["convert", str(path), "--fov", f"{horizontal:.6f}", "--out", str(out)]
    with pytest.warns(UserWarning) as record:
        assert main(argv) == 0
    (message,) = [str(w.message) for w in record if w.category is UserWarning]
    assert message.startswith(f"fov: --fov {horizontal:.6g} is read as the vertical field of view, but the normals "
                              "fit the depth far better") and message.endswith("if so, give --fov 60"), message
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        assert main(["convert", str(path), "--fov", "60", "--out", str(out)]) == 0
    # on the command line: one line on stderr
    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[1]), "PATH": "/usr/bin:/bin"}
    proc = subprocess.run([sys.executable, "-m", "torch_ao", *argv], capture_output=True, text=True, env=env)
    assert proc.returncode == 0 and proc.stderr == f"torch-ao convert: warning: {message}\n", proc.stderr

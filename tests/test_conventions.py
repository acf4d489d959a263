"""Conventions that cannot go silently wrong: each common mistake reading an engine's G-buffer either
gives the right AO or one error line naming the flag that fixes it."""
import argparse

import numpy as np
import pytest
import torch

from torch_ao.cli import build_parser, main
from torch_ao.engine_io import ENGINE_OPTIONS


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
    assert main(argv + ["--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip() == message
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------- shared fixtures
from torch_ao import GBuffer, gtao, load_gbuffer, save_npz  # noqa: E402
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

"""Resource limits (torch_ao.limits): what cannot fit in memory is refused by name and with the limit,
before it is allocated, from small synthetic files whose headers claim huge sizes."""
from __future__ import annotations

import io
import struct
import zipfile
import zlib

import numpy as np
import pytest
import torch

import torch_ao
from torch_ao.camera import PinholeCamera
from torch_ao.cli import main
from torch_ao.gbuffer import GBuffer
from torch_ao.io import read_npz
from torch_ao.limits import LIMITS, ResourceLimitError, limit, walk_bytes


def _npy_header(shape, dtype="<f4") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": tuple(shape)})
    return buf.getvalue()


def _npz(path, members: dict[str, bytes], compress=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compress) as zf:
        for key, data in members.items():
            zf.writestr(key + ".npy", data)
    return path


def test_defaults_and_environment_override(monkeypatch):
    assert limit("image_pixels") == 1 << 28
    monkeypatch.setenv("TORCH_AO_MAX_IMAGE_PIXELS", "1e6")
    assert limit("image_pixels") == 10 ** 6
    monkeypatch.setenv("TORCH_AO_MAX_IMAGE_PIXELS", "lots")
    with pytest.raises(ValueError, match=r"^TORCH_AO_MAX_IMAGE_PIXELS: expected a positive number, got 'lots'$"):
        limit("image_pixels")
    assert set(LIMITS) == {"image_pixels", "array_bytes", "walk_bytes"}


def test_npz_header_claiming_100000_squared_is_refused_unread(tmp_path):
    path = _npz(tmp_path / "huge.npz", {"depth": _npy_header((100000, 100000)) + b"\0" * 64})
    with pytest.raises(ResourceLimitError) as err:
        read_npz(path)
    assert str(err.value) == (f"path: {path}: member 'depth' of shape (100000, 100000): needs 10,000,000,000 pixels, "
                              "above the limit of 268,435,456 pixels (TORCH_AO_MAX_IMAGE_PIXELS raises it)")


def test_npz_shorter_than_its_header_is_truncated_not_pickled(tmp_path):
    path = _npz(tmp_path / "cut.npz", {"depth": _npy_header((4, 4)) + b"\0" * 10})
    with pytest.raises(ValueError) as err:
        read_npz(path)
    assert "pickled" not in str(err.value)
    assert str(err.value) == (f"path: {path}: member 'depth' is truncated: its header says (4, 4) float32 (64 bytes), "
                              "the member holds 10")


def test_npz_object_member_is_refused_as_pickled(tmp_path):
    path = _npz(tmp_path / "obj.npz", {"depth": _npy_header((2,), "|O") + b"\0" * 16})
    with pytest.raises(ValueError, match=r"member 'depth' holds pickled objects \(object\), which are refused"):
        read_npz(path)


def test_zip_bomb_is_refused_from_the_uncompressed_size(tmp_path, monkeypatch):
    """A 64 MiB member of zeros, about 64 KiB compressed, under a 16 MiB limit: refused without inflating."""
    header = _npy_header((4096, 4096))
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("depth.npy", "w", force_zip64=True) as f:
            f.write(header)
            zero = bytes(1 << 20)
            for _ in range(64):
                f.write(zero)
    assert path.stat().st_size < 1 << 20
    monkeypatch.setenv("TORCH_AO_MAX_ARRAY_BYTES", str(16 << 20))
    with pytest.raises(ResourceLimitError, match=r"^path: .*bomb.npz \(1 arrays, uncompressed\): needs 64 MiB, above the "
                       r"limit of 16 MiB \(TORCH_AO_MAX_ARRAY_BYTES raises it\)$"):
        read_npz(path)


def test_zip_bomb_claiming_3_35_gib_under_the_default(tmp_path, monkeypatch):
    """The issue's 3.35 GiB bomb, its size as the zip's directory states it (patched, nothing inflated)."""
    path = _npz(tmp_path / "bomb.npz", {"depth": _npy_header((1, 30000, 30000)) + b"\0" * 16})
    data = bytearray(path.read_bytes())
    size = 3_600_000_128  # 3.35 GiB
    for sig, offset in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):  # local header and central directory
        at = data.find(sig)
        data[at + offset:at + offset + 4] = struct.pack("<I", size)
    path.write_bytes(bytes(data))
    monkeypatch.setenv("TORCH_AO_MAX_IMAGE_PIXELS", str(10 ** 9))  # the byte limit alone
    monkeypatch.setenv("TORCH_AO_MAX_ARRAY_BYTES", str(2 << 30))
    with pytest.raises(ResourceLimitError, match=r"needs 3.35 GiB, above the limit of 2 GiB"):
        read_npz(path)


def test_cli_refuses_a_huge_npz_in_one_line(tmp_path, capsys):
    path = _npz(tmp_path / "huge.npz", {"depth": _npy_header((100000, 100000)) + b"\0" * 64})
    out = tmp_path / "o.npz"
    assert main(["ao", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"torch-ao ao: error: path: {path}: member 'depth'") and err.count("\n") == 1
    assert not out.exists()


def _patched_exr(tmp_path, width, height):
    OpenEXR = pytest.importorskip("OpenEXR")
    path = tmp_path / "big.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Z": np.ones((4, 4), np.float32)}).write(str(path))
    data = bytearray(path.read_bytes())
    at = data.find(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4  # after the attribute's size
    data[at:at + 16] = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    path.write_bytes(bytes(data))
    return path


def test_exr_data_window_200000_squared_is_refused_from_the_header(tmp_path, capsys):
    path = _patched_exr(tmp_path, 200000, 200000)
    out = tmp_path / "o.npz"
    assert main(["ao", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"torch-ao ao: error: path: {path}: part 0's data window (200000x200000): needs 40,000,000,000 "
                   "pixels, above the limit of 268,435,456 pixels (TORCH_AO_MAX_IMAGE_PIXELS raises it)\n")
    assert not out.exists()


def _png(width, height, idat=b"") -> bytes:
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0))
            + chunk(b"IDAT", idat or zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def test_png_decompression_bomb_is_refused_from_its_header(tmp_path, capsys):
    pytest.importorskip("PIL")
    path = tmp_path / "bomb.png"
    path.write_bytes(_png(100000, 100000))
    out = tmp_path / "o.npz"
    assert main(["ao", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"torch-ao ao: error: path: {path} (100000x100000 PNG): needs 10,000,000,000 pixels, above the "
                   "limit of 268,435,456 pixels (TORCH_AO_MAX_IMAGE_PIXELS raises it)\n")
    assert not out.exists()


def test_walk_estimate_refuses_8192_squared_and_takes_2048_squared(monkeypatch):
    monkeypatch.setenv("TORCH_AO_MAX_WALK_BYTES", str(8 << 30))
    for n, refused in ((2048, False), (8192, True)):
        gb = GBuffer(torch.ones(1, 1, 1, 1).expand(1, 1, n, n), PinholeCamera.from_fov(60.0, n, n))  # nothing allocated
        with torch.no_grad():
            if refused:
                with pytest.raises(ResourceLimitError, match=r"^GTAO: 1x8192x8192 pixels at 4 slices x 8 steps: needs 80 GiB, "
                                   r"above the limit of 8 GiB \(TORCH_AO_MAX_WALK_BYTES raises it; or give chunk_size"):
                    torch_ao.GTAO(slices=4, steps=8).check_memory(gb)
            else:
                torch_ao.GTAO(slices=4, steps=8).check_memory(gb)


def test_walk_estimate_formula():
    assert walk_bytes(1, 10, 10, 4, 8, grad=False) == 100 * (256 + 128 * 8)
    assert walk_bytes(1, 10, 10, 4, 8, grad=True) == 100 * (256 + 128 * 8 + 256 * 32)
    assert walk_bytes(1, 10, 10, 4, 8, grad=True, chunk_size=10, recompute=True) == 100 * 256 + 10 * (128 * 8 + 256 * 32)


def test_cli_walk_limit_names_the_method(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TORCH_AO_MAX_WALK_BYTES", "100000")
    out = tmp_path / "o.npz"
    assert main(["ao", "--method", "bitmask", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torch-ao ao: error: BitmaskAO: ") and "TORCH_AO_MAX_WALK_BYTES" in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["ao", "--slices", "1000000000"], "argument --slices: expected an integer <= 64, got 1000000000"),
    (["ao", "--steps", "4096"], "argument --steps: expected an integer <= 256, got 4096"),
    (["render", "sphere_on_plane", "--spp", "100000000"], "argument --spp: expected an integer <= 65536, got 100000000"),
])
def test_counts_above_their_maxima_exit_2(argv, message, tmp_path, capsys):
    out = tmp_path / "o.npz"
    assert main(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not out.exists()


def test_python_api_refuses_the_counts_by_name():
    with pytest.raises(ValueError, match=r"^slices: expected an integer <= 64, got 4096$"):
        torch_ao.BitmaskAO(slices=4096)
    from torch_ao.reference import get_scene, render_reference
    from torch_ao.reference.views import look_at
    with pytest.raises(ValueError, match=r"^spp: expected an integer in \[2, 65536\]"):
        render_reference(get_scene("sphere_on_plane"), look_at((0, 1, 3), (0, 0, 0), height=4, width=4), spp=10 ** 8)

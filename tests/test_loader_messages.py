"""The loaders' messages name the key and the file: strings, booleans and complex numbers where numbers
belong (.npz camera keys, EXR header attributes, a glTF camera's yfov), options given as a list in
params.json; complex intrinsics are refused, never cut to their real part."""
from __future__ import annotations

import json

import numpy as np
import pytest

from torch_ao.cli import main
from torch_ao.fitted import FittedPipeline, load_fitted
from torch_ao.io import load_gbuffer
from torch_ao.reference import gltf_camera

DEPTH = np.full((4, 6), 2.0, np.float32)
K = np.array([[5.0, 0, 2.5], [0, 5.0, 1.5], [0, 0, 1]])


@pytest.mark.parametrize("key, value, shown", [
    ("fov_y_degrees", np.array("60"), "<U2 ['60']"),
    ("fov_y_degrees", np.array(True), "bool [True]"),
    ("intrinsics", K * (1 + 1e-3j), "complex128 [(5+0.005j), 0j, (2.5+0.0025j), 0j]"),
    ("intrinsics", K.astype(str), "<U32 ['5.0', '0.0', '2.5', '0.0']"),
])
def test_npz_camera_keys_must_be_real_numbers(key, value, shown, tmp_path, capsys):
    path = tmp_path / "g.npz"
    np.savez(path, depth=DEPTH, **{key: value})
    with pytest.raises(ValueError) as err:
        load_gbuffer(path)
    assert str(err.value) == f"{key}: expected real numbers in {path}, got {shown}"
    assert main(["ao", str(path), "--out", str(tmp_path / "o.npz")]) == 2
    assert capsys.readouterr().err == f"torch-ao ao: error: {key}: expected real numbers in {path}, got {shown}\n"
    assert not (tmp_path / "o.npz").exists()


def test_bad_intrinsics_values_name_the_file(tmp_path):
    path = tmp_path / "g.npz"
    bad = K.copy()
    bad[0, 0] = 1e-20
    np.savez(path, depth=DEPTH, intrinsics=bad)
    with pytest.raises(ValueError, match=rf"^intrinsics: fx must be in .* got 1e-20 \(in {path}\)$"):
        load_gbuffer(path)


@pytest.mark.parametrize("attribute", ["intrinsics", "fov_y_degrees", "worldToCamera"])
def test_exr_header_attributes_must_be_numbers(attribute, tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    path = tmp_path / "g.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, attribute: "wide"}
    OpenEXR.File(header, {"Z": DEPTH}).write(str(path))
    with pytest.raises(ValueError) as err:
        load_gbuffer(path, fov=60.0)
    assert str(err.value) == f"{attribute} (header attribute): expected real numbers in {path}, got <U4 ['wide']"


def test_engine_option_intrinsics_complex_refused():
    from torch_ao.io.engine import EngineOptions

    with pytest.raises(ValueError, match=r"^intrinsics: expected real numbers in the engine options, got complex128"):
        EngineOptions(intrinsics=(5 + 1j, 5.0, 2.5, 1.5))


@pytest.mark.parametrize("camera, message", [
    ({"type": "perspective"}, "cameras[0].perspective.yfov: a perspective camera needs its 'perspective' block with 'yfov'"),
    ({"type": "perspective", "perspective": {"yfov": "0.8"}}, "cameras[0].perspective.yfov: expected a number, got '0.8' (radians)"),
    ({"type": "perspective", "perspective": {"yfov": 0.0}}, "cameras[0].perspective.yfov: expected a number > 0.0, got 0.0 (radians)"),
    ({"type": "perspective", "perspective": {"yfov": [1]}}, "cameras[0].perspective.yfov: expected a number, got [1] (radians)"),
])
def test_gltf_yfov_names_the_key_and_the_file(camera, message, tmp_path):
    path = tmp_path / "c.gltf"
    path.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"camera": 0}], "cameras": [camera]}))
    with pytest.raises(ValueError) as err:
        gltf_camera(path)
    assert str(err.value) == f"mesh: {path}: {message}"


def test_gltf_yfov_valid():
    import math
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "c.gltf"
        path.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"camera": 0}],
                                    "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5}}]}))
        assert gltf_camera(path).fov_y_degrees == pytest.approx(math.degrees(0.5))


@pytest.mark.parametrize("key, value, shown", [
    ("options", [["radius", 1.0]], "list [['radius', 1.0]]"),
    ("options", ["a"], "list ['a']"),
    ("parameters", "radius", "str 'radius'"),
])
def test_params_json_sections_must_be_objects(key, value, shown, tmp_path):
    path = tmp_path / "params.json"
    path.write_text(json.dumps(FittedPipeline("gtao", {"radius": 1.0}).to_dict() | {key: value}))
    with pytest.raises(ValueError) as err:
        load_fitted(path)
    assert str(err.value) == f"fitted: {path}: '{key}' must be an object ({{name: value}}), got {shown}"

"""Fault and bad-input suite over every input format and every command-line flag's bounds.

Each property draws a mutation of a valid input (a .npz G-buffer's members, dtypes and shapes; a
params.json's values and types; an OpenEXR file's header attributes; a Mitsuba scene's attributes; a
glTF camera) and asserts the only two outcomes allowed: a correct result (finite, visibility in [0, 1])
or a ``ValueError`` whose message names the file. Never another exception type, never NaN, never a
file outside the scene's folder. Example counts are small (the suite runs in seconds); the flag
bounds are parametrised over the flags' :class:`~torch_ao.options.Option` ranges.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torch_ao
from torch_ao.cli import build_parser, main
from torch_ao.fitted import FittedPipeline, load_fitted
from torch_ao.io import load_gbuffer

FAST = settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
H, W = 6, 8


def _valid_arrays() -> dict[str, np.ndarray]:
    from torch_ao.examples import example_gbuffer

    gb = example_gbuffer(H, W)
    return {"depth": gb.depth[0, 0].numpy(), "normal": gb.normals[0].permute(1, 2, 0).numpy(),
            "intrinsics": gb.camera.intrinsics[0].numpy(), "mask": np.ones((H, W), bool),
            "object_id": np.arange(H * W).reshape(H, W) % 3}


def _method():
    return torch_ao.GTAO(slices=2, steps=2, radius=1.0)


def _written_then_checked(name: str, write, run) -> str:
    """``write(path)`` a file ``name`` in a fresh folder, then assert that ``run(path)`` either returns a
    finite visibility in [0, 1] or raises a one-line ValueError naming ``path``."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        write(path)
        return _assert_outcome(lambda: run(path), path)


def _assert_outcome(run, path):
    """``run()`` either returns a finite visibility in [0, 1] or raises ValueError naming ``path``."""
    try:
        vis = run()
    except ValueError as err:
        assert str(path) in str(err), f"the message does not name the file: {err}"
        assert "\n" not in str(err).strip(), err
        return "refused"
    assert torch.isfinite(vis).all(), "NaN or inf returned"
    assert float(vis.min()) >= 0 and float(vis.max()) <= 1
    return "ok"


# ---------------------------------------------------------------------------------------- .npz
DTYPES = ["float16", "float32", "float64", "int8", "int64", "uint16", "bool", "complex64", "<U3"]
SPECIAL = [float("nan"), float("inf"), -float("inf"), 0.0, -1.0, 1e-30, 1e15, 3.4e38, -0.0]


@st.composite
def npz_mutations(draw):
    arrays = _valid_arrays()
    key = draw(st.sampled_from(sorted(arrays)))
    kind = draw(st.sampled_from(["drop", "dtype", "shape", "values", "scalar", "empty"]))
    a = arrays[key]
    if kind == "drop":
        del arrays[key]
    elif kind == "dtype":
        dtype = draw(st.sampled_from(DTYPES))
        arrays[key] = a.astype(dtype) if dtype != "<U3" else a.astype(str)
    elif kind == "shape":
        shape = draw(st.sampled_from([(W, H), (1, H, W), (2, H, W), (H, W, 1), (H - 1, W), (H * W,), (H, W, 2), (3,)]))
        arrays[key] = np.resize(a, shape)
    elif kind == "values" and a.dtype.kind == "f":
        a = a.copy()
        flat = a.reshape(-1)
        for i in draw(st.lists(st.integers(0, flat.size - 1), min_size=1, max_size=4)):
            flat[i] = draw(st.sampled_from(SPECIAL))
        arrays[key] = a
    elif kind == "scalar":
        arrays[key] = np.array(draw(st.sampled_from(SPECIAL)))
    elif kind == "empty":
        arrays[key] = np.zeros((0,) + a.shape[1:], a.dtype)
    return arrays


@FAST
@given(npz_mutations())
def test_mutated_npz_gives_a_result_or_a_value_error_naming_the_file(arrays):
    def run(path):
        gb, _ = load_gbuffer(path)
        with torch.no_grad():
            return _method()(gb).visibility
    _written_then_checked("g.npz", lambda path: np.savez(path, **arrays), run)


# ---------------------------------------------------------------------------------------- params.json
JSON_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 6, 10 ** 6), st.sampled_from([1e308, -1e-300, 0.0, 0.5, 1e-9]),
                        st.text(max_size=4), st.lists(st.integers(0, 3), max_size=3),
                        st.dictionaries(st.sampled_from(["shape", "values", "x"]), st.integers(0, 3), max_size=2))


@st.composite
def params_mutations(draw):
    method = draw(st.sampled_from(["gtao", "bitmask", "hbao"]))
    data = FittedPipeline(method, {"preset": "low", "radius": 1.0}, denoiser=draw(st.booleans())).to_dict()
    section = draw(st.sampled_from(["options", "parameters", "top", "denoiser"]))
    value = draw(JSON_VALUES)
    if section == "top":
        data[draw(st.sampled_from(sorted(data)))] = value
    elif isinstance(data.get(section), dict) and data[section]:
        data[section][draw(st.sampled_from(sorted(data[section])))] = value
    else:
        data[section] = value
    return data


@FAST
@given(params_mutations())
def test_mutated_params_json_gives_a_pipeline_or_a_value_error_naming_the_file(data):
    from torch_ao.examples import example_gbuffer

    def run(path):
        with torch.no_grad():
            return load_fitted(path)(example_gbuffer(H, W)).visibility
    _written_then_checked("params.json", lambda path: path.write_text(json.dumps(data)), run)


# ---------------------------------------------------------------------------------------- OpenEXR
EXR_VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.text(max_size=3),
                       st.lists(st.floats(-1e3, 1e3, width=32), min_size=1, max_size=9))


@FAST
@given(st.sampled_from(["intrinsics", "fov_y_degrees", "worldToCamera"]), EXR_VALUES)
def test_exr_header_attributes_give_a_result_or_a_value_error(attribute, value):
    OpenEXR = pytest.importorskip("OpenEXR")
    from torch_ao.examples import example_gbuffer

    depth = example_gbuffer(H, W).depth[0, 0].numpy()
    if isinstance(value, list):
        value = np.array(value, np.float32)
        if value.size == 9:
            value = value.reshape(3, 3)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, attribute: value}
    try:
        OpenEXR.File(header, {"Z": depth})
    except (TypeError, ValueError, RuntimeError):
        return  # the binding cannot hold this attribute: nothing to read

    def run(path):
        gb, _ = load_gbuffer(path, **({} if attribute != "worldToCamera" else {"fov": 60.0}))
        with torch.no_grad():
            return _method()(gb).visibility
    _written_then_checked("g.exr", lambda path: OpenEXR.File(header, {"Z": depth}).write(str(path)), run)


# ---------------------------------------------------------------------------------------- Mitsuba
FILENAMES = st.one_of(st.sampled_from(["box.obj", "sub/box.obj", "../box.obj", "/etc/passwd", "$f", "$fx", "./box.obj",
                                       "sub/../box.obj", "sub/../../box.obj", "link.obj", "~/box.obj", ""]),
                      st.text(alphabet="ab./$", min_size=1, max_size=6))
DEFAULTS = st.sampled_from(["box.obj", "../box.obj", "/etc/passwd", "sub/box.obj", "$f"])


def _outside(folder: Path, name: str) -> bool:
    """Independent of the library: does ``name`` resolve outside ``folder``?"""
    real = os.path.realpath(os.path.join(folder, os.path.expanduser(name)))
    return not (real == str(folder) or real.startswith(str(folder) + os.sep))


@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(FILENAMES, DEFAULTS, st.sampled_from(["include", "shape"]))
def test_mitsuba_references_outside_are_always_refused(name, default, element):
    pytest.importorskip("mitsuba")
    from torch_ao.reference import mesh_scene
    from torch_ao.io.confine import OutsidePathError

    with tempfile.TemporaryDirectory() as d:
        root = Path(d).resolve() / "scene"
        (root / "sub").mkdir(parents=True)
        box = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
        for p in (root / "box.obj", root / "sub" / "box.obj", root.parent / "box.obj"):
            p.write_text(box)
        os.symlink(root.parent / "box.obj", root / "link.obj")
        ref = (f'<include filename="{name}"/>' if element == "include"
               else f'<shape type="obj"><string name="filename" value="{name}"/></shape>')
        xml = root / "scene.xml"
        xml.write_text(f'<scene version="3.0.0"><default name="f" value="{default}"/>{ref}<shape type="sphere"/></scene>')
        resolved = name.replace("$f", default)
        try:
            mesh_scene([xml])
        except OutsidePathError:
            return
        except ValueError as err:
            assert str(xml) in str(err) or "scene" in str(err), err
            assert not _outside(root, resolved) or "$" in resolved, f"{resolved!r} reached Mitsuba: {err}"
            return
        assert not _outside(root, resolved), f"{resolved!r} is outside and was read"


# ---------------------------------------------------------------------------------------- glTF cameras
CAMERA_VALUES = st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3),
                          st.lists(st.floats(-2, 2), max_size=3), st.dictionaries(st.sampled_from(["yfov", "znear"]), st.floats(-4, 4)))


@st.composite
def gltf_cameras(draw):
    camera = {"type": draw(st.sampled_from(["perspective", "orthographic", 3, None])),
              "perspective": {"yfov": draw(st.one_of(st.floats(-1, 4), CAMERA_VALUES)), "znear": 0.01}}
    key = draw(st.sampled_from(["perspective", "yfov", "none"]))
    if key == "perspective":
        camera["perspective"] = draw(CAMERA_VALUES)
    elif key == "yfov":
        del camera["perspective"]["yfov"]
    node = {"camera": draw(st.sampled_from([0, 1, -1, "0", None])),
            "translation": draw(st.sampled_from([[0, 0, 3], [0, 0], "x"]))}
    return {"asset": {"version": "2.0"}, "nodes": [node], "cameras": [camera]}


@FAST
@given(gltf_cameras())
def test_gltf_cameras_give_a_view_or_a_value_error_naming_the_file(header):
    from torch_ao.reference import gltf_camera

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "c.gltf"
        path.write_text(json.dumps(header))
        try:
            view = gltf_camera(path)
        except ValueError as err:
            assert str(path) in str(err), err
            return
        if view is not None:
            assert 0 < view.fov_y_degrees < 180 and all(math.isfinite(x) for x in (*view.eye, *view.target, *view.up))


# ---------------------------------------------------------------------------------------- flag bounds
def _flag_bounds():
    """``(command, flag, extra argv, value)`` just outside every bound of every numeric flag built from an Option."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and isinstance(a.choices, dict))
    cases = []
    for command, p in sub.choices.items():
        has_method = any(a.dest == "method" for a in p._actions)
        for action in p._actions:
            owners = getattr(action.type, "options", None)
            if not owners or not action.option_strings:
                continue
            for owner, opt in owners.items():
                if opt.kind not in (int, float) or opt.choices:
                    continue
                extra = ["--method", owner] if owner and has_method else []
                if owner and not has_method:
                    continue
                for bound, below in ((opt.minimum, True), (opt.maximum, False)):
                    if bound is None:
                        continue
                    open_ = opt.open_minimum if below else opt.open_maximum
                    if opt.kind is int:
                        value = bound - 1 if below else bound + 1
                    elif open_:
                        value = bound
                    else:
                        value = bound - max(abs(bound) * 1e-6, 1e-9) if below else bound + max(abs(bound) * 1e-6, 1e-9)
                    cases.append(pytest.param(command, action.option_strings[0], extra, repr(value),
                                              id=f"{command}{action.option_strings[0]}{'@' + owner if owner else ''}{'<' if below else '>'}"))
    return cases


FLAG_BOUNDS = _flag_bounds()


def test_the_bounds_cover_the_commands():
    commands = {p.values[0] for p in FLAG_BOUNDS}
    flags = {p.values[1] for p in FLAG_BOUNDS}
    assert {"ao", "render", "fit", "bench", "convert"} <= commands
    assert {"--slices", "--steps", "--spp", "--radius", "--width", "--thickness"} <= flags
    assert len(FLAG_BOUNDS) > 60


@pytest.mark.parametrize("command, flag, extra, value", FLAG_BOUNDS)
def test_every_flag_just_outside_its_range_exits_2_naming_it(command, flag, extra, value, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([command, f"{flag}={value}", *extra, "--out", str(out / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert flag in err and err.count("\n") == 1, err
    assert not out.exists()

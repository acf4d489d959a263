"""Units: a fitted pipeline applied with ``scale`` to a frame ``scale`` times larger gives the same AO.

``scale_lengths`` multiplies every option whose unit is world units (and divides those in 1 / world
units), so with all positions and depths x100 and ``--scale 100`` every method computes the same
visibility up to float rounding.
"""
from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from torch_ao.cli import main
from torch_ao.fitted import DEFAULT_LENGTH_UNIT, FittedPipeline, length_factors, load_fitted, scale_lengths
from torch_ao.gbuffer import GBuffer

SCALE = 100.0
CASES = {  # name: (method, options)
    "gtao": ("gtao", {"preset": "high", "radius": 0.7, "falloff_range": 0.3}),
    "hbao": ("hbao", {"preset": "high", "radius": 0.8}),
    "bitmask_scalar": ("bitmask", {"preset": "high", "weighting": "cosine", "radius": 0.6, "thickness": 0.2,
                                   "thickness_growth": 0.5}),
    "bitmask_backface": ("bitmask", {"preset": "high", "variant": "exact", "thickness_model": "backface",
                                     "thickness_scale": 0.8, "thickness": 0.1, "radius": 0.6}),
    "ssao": ("ssao", {"preset": "high", "radius": 0.5, "bias": 0.03, "softness": 0.01}),
    "ue4_ssao": ("ue4_ssao", {"preset": "high", "radius": 0.9, "fade_distance": 0.3, "flat_surface_bias": 0.02}),
    # the published defaults: bias, flat_surface_bias and UE4's radius (nearest fetch) are buffers there
    "ssao_default": ("ssao", {"preset": "high"}),
    "ue4_ssao_default": ("ue4_ssao", {"preset": "high"}),
}


@pytest.fixture(scope="module")
def frame():
    from torch_ao.reference import get_scene, render_reference

    ref = render_reference(get_scene("stairs", seed=1000), height=48, width=80, spp=2, uniform=False,
                           progress=False, backface=True)
    return replace(ref.gbuffer, backface_depth=ref.backface_depth)


def scaled(gb: GBuffer, s: float) -> GBuffer:
    """The same frame with every position and depth ``s`` times larger (normals and camera unchanged)."""
    return replace(gb, depth=gb.depth * s, backface_depth=None if gb.backface_depth is None else gb.backface_depth * s)


def test_every_length_option_is_scaled():
    assert length_factors("bitmask") == {"radius": 1, "thickness": 1, "thickness_growth": -1}
    assert length_factors("ssao") == {"radius": 1, "bias": 1, "softness": 1}
    assert length_factors("ue4_ssao") == {"radius": 1, "fade_distance": 1, "flat_surface_bias": 1, "flat_softness": 1}
    assert length_factors("gtao") == {"radius": 1}  # falloff_range is a fraction of it; max_radius_px pixels
    assert length_factors("pssao") == {"distance_bias": 1}
    out = scale_lengths("bitmask", {"radius": 0.5, "thickness": {"shape": [2], "values": [0.1, 0.3]},
                                    "thickness_scale": 0.8, "thickness_growth": 2.0, "preset": "high"}, 10.0)
    assert out == {"radius": 5.0, "thickness": {"shape": [2], "values": [1.0, 3.0]}, "thickness_scale": 0.8,
                   "thickness_growth": 0.2, "preset": "high"}


@pytest.mark.parametrize("name", tuple(CASES))
def test_scaled_pipeline_on_a_scaled_frame_gives_the_same_ao(name, frame, tmp_path):
    method, options = CASES[name]
    path = tmp_path / "params.json"
    FittedPipeline(method, options).save(path)
    with torch.no_grad():
        base = load_fitted(path)(frame).visibility
        big = load_fitted(path, scale=SCALE)(scaled(frame, SCALE)).visibility
        unscaled = load_fitted(path)(scaled(frame, SCALE)).visibility
    diff = (base - big).abs()
    assert float(diff.max()) < 1e-4, float(diff.max())
    # and without --scale the larger frame is another result (so the test can fail)
    assert float((base - unscaled).abs().mean()) > 1e-2


def test_ao_fitted_scale_flag(frame, tmp_path, capsys):
    from torch_ao.io import load_gbuffer, save_npz

    params = tmp_path / "params.json"
    FittedPipeline(*CASES["bitmask_scalar"], True).save(params)
    small, big = tmp_path / "m.npz", tmp_path / "cm.npz"
    save_npz(small, frame)
    save_npz(big, scaled(frame, SCALE))
    assert main(["ao", str(small), "--fitted", str(params), "--out", str(tmp_path / "a.npz")]) == 0
    assert main(["ao", str(big), "--fitted", str(params), "--scale", "100", "--out", str(tmp_path / "b.npz")]) == 0
    a = load_gbuffer(tmp_path / "a.npz")[1]["visibility"]
    b = load_gbuffer(tmp_path / "b.npz")[1]["visibility"]
    assert float((torch.as_tensor(a) - torch.as_tensor(b)).abs().max()) < 1e-4
    capsys.readouterr()
    assert main(["ao", str(small), "--scale", "100", "--out", str(tmp_path / "c.npz")]) == 2
    assert capsys.readouterr().err == ("torch-ao ao: error: --scale: scales a --fitted pipeline's lengths; give "
                                       "--radius (and the other lengths) directly without --fitted\n")
    assert not (tmp_path / "c.npz").exists()


def test_params_json_records_its_length_unit_and_old_files_still_load(tmp_path):
    path = tmp_path / "params.json"
    FittedPipeline("gtao", {"preset": "high"}, length_unit="m").save(path)
    data = json.loads(path.read_text())
    assert data["length_unit"] == "m"
    assert load_fitted(path).length_unit == "m"
    del data["length_unit"]  # a file written before the key existed
    path.write_text(json.dumps(data))
    assert load_fitted(path).length_unit == DEFAULT_LENGTH_UNIT == "world units"
    with pytest.raises(ValueError, match=r"^scale: expected a positive number \(world units per fitted unit\), got 0$"):
        load_fitted(path, scale=0)

"""The hard kernel of bitmask AO's ``"default"`` variant with the edge-aware fetch and the back-face
thickness layer (bitmask.h's BitmaskAccumulator reading bitmask.h's ThicknessModel, walk.h's edge-aware
taps) against the tensor-op walk, by the tolerance of tests/kernel_agreement.py, in SIMD and scalar lanes."""
import pytest
import torch

from kernel_agreement import assert_masks_agree, assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture)
from test_kernels_exact import with_backface
from torch_ao.kernels import kernel_covers, kernel_forward
from torch_ao.kernels.bitmask import bitmask_outputs, module_thickness, thickness_options
from torch_ao.methods.bitmask import SSILVB, BitmaskAO
from torch_ao.thickness import BackfaceThickness

SETTINGS = [
    dict(slices=3, steps=4, fetch="edge_aware"),
    dict(slices=2, steps=5, thickness=BackfaceThickness(scale=0.8, thickness=0.05)),
    dict(slices=3, steps=3, fetch="edge_aware", thickness=BackfaceThickness(), border="clamp", seed=2),
]


def _kernel(module: BitmaskAO, gb, lanes: str):
    if lanes == "simd":
        return kernel_forward(module, gb, "kernel")
    out = bitmask_outputs(gb, gb.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                          radius=float(module.radius), **thickness_options(module_thickness(module, gb)),
                          step_power=module.step_power,
                          min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, fetch=module.fetch,
                          border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon,
                          weighting=module.weighting, indirect=module.want_indirect, variant=module.variant,
                          azimuth=module.azimuth, noise=module.noise, stagger=module.stagger, lanes="scalar")
    return {"visibility": out.visibility, "indirect": out.indirect}


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_uniform_visibility_agrees_with_the_tensor_walk(built, frame, setting, lanes):
    gb = with_backface(FRAMES[frame]())
    module = BitmaskAO(mode="hard", backend="torch", trainable=False, **SETTINGS[setting])
    with torch.no_grad():
        reference = module(gb).visibility
        assert kernel_covers(module, gb) is None
        out = _kernel(module, gb, lanes)["visibility"]
    assert reference.min() < 1  # something is occluded: the comparison means something
    assert_masks_agree(out, reference, gb.valid, module.slices)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", ["example", "rough"])
def test_cosine_visibility_and_indirect_light_agree_with_the_tensor_walk(built, frame, lanes):
    """What ``torch-ao fit`` can choose: cosine sectors, the edge-aware fetch and the back-face layer, with
    the indirect light of the sectors (a second frame buffer read through the same taps)."""
    gb = with_backface(FRAMES[frame]())
    gb = type(gb)(depth=gb.depth, camera=gb.camera, normals=gb.normals, backface_depth=gb.backface_depth,
                  light=torch.rand(gb.depth.shape[0], 3, *gb.depth.shape[2:], generator=torch.Generator().manual_seed(1)))
    module = BitmaskAO(mode="hard", backend="torch", trainable=False, slices=3, steps=4, weighting="cosine",
                       fetch="edge_aware", thickness=BackfaceThickness(scale=1.2), indirect=True)
    with torch.no_grad():
        reference = module(gb)
        out = _kernel(module, gb, lanes)
    assert reference.visibility.min() < 0.9 and reference.indirect.max() > 0
    assert_values_agree(out["visibility"], reference.visibility, gb.valid, bound=1 / (32 * 3) + 1e-6)
    assert_values_agree(out["indirect"], reference.indirect, gb.valid, bound=0.05)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("variant, model", [("default", "scalar"), ("default", "backface"), ("hdrp", "scalar")])
def test_a_thickness_growth_agrees_with_the_tensor_walk(built, variant, model, lanes):
    """``thickness_growth`` (the thickness times ``1 + g |sample - pixel|``) in the hard kernels: uniform visibility,
    cosine weights with indirect light and bent normals; it changes the masks on this frame. Uniform masks against
    the float32 walk (share 0.998 for ``hdrp``, as tests/test_kernels_hdrp.py), the rest against the float64 walk (the
    float32 walk's ``hdrp`` slice angle is off where the normal faces the view vector)."""
    gb = with_backface(FRAMES["rough"]())
    gb = type(gb)(depth=gb.depth, camera=gb.camera, normals=gb.normals, backface_depth=gb.backface_depth,
                  light=torch.rand(gb.depth.shape[0], 3, *gb.depth.shape[2:], generator=torch.Generator().manual_seed(1)))

    def thickness():  # (a model takes the module's growth: one each)
        return 0.3 if model == "scalar" else BackfaceThickness(scale=0.8, thickness=0.05)

    for options in (dict(), dict(weighting="cosine", indirect=True, bent_normals=True)):
        module = BitmaskAO(variant=variant, mode="hard", backend="torch", trainable=False, slices=3, steps=4,
                           thickness=thickness(), thickness_growth=2.0, **options)
        with torch.no_grad():
            assert kernel_covers(module, gb) is None
            reference = module(gb) if not options else module.double()(gb.to(dtype=torch.float64))
            out = _kernel(module.float(), gb, lanes) if not options else kernel_forward(module.float(), gb, "kernel")
            out = {name: value.to(reference.visibility.dtype) for name, value in out.items() if value is not None}
            plain = BitmaskAO(variant=variant, slices=3, steps=4, thickness=thickness(), backend="kernel",
                              trainable=False, **options)(gb)
        assert (plain.visibility - reference.visibility).abs().max() > 0.02
        if not options:
            assert_masks_agree(out["visibility"], reference.visibility, gb.valid, slices=3,
                               share=0.998 if variant == "hdrp" else 0.999)
            continue
        assert_values_agree(out["visibility"], reference.visibility, gb.valid, bound=1 / (32 * 3) + 1e-6)
        assert_values_agree(out["indirect"], reference.indirect, gb.valid, bound=0.05)
        assert_values_agree(out["bent_normal"], reference.bent_normal, gb.valid, bound=0.1)


def test_the_glsl_shaders_thickness_grows_as_the_tensor_walks(built):
    from test_kernels_glsl import assert_glsl_agrees, lit

    gb = lit(FRAMES["rough"]())
    options = dict(variant="ssilvb_glsl", slices=3, steps=4, thickness=0.2, thickness_growth=3.0, trainable=False)
    with torch.no_grad():
        module = SSILVB(backend="kernel", **options)
        assert kernel_covers(module, gb) is None
        out = module(gb)
        reference = SSILVB(backend="torch", **options)(gb)
        plain = SSILVB(backend="kernel", **dict(options, thickness_growth=None))(gb)
    assert (plain.visibility - reference.visibility).abs().max() > 0.02
    assert_glsl_agrees(out, reference, gb.valid, slices=3)


def test_the_new_options_change_the_visibility(built):
    """Each option the comparison above covers changes the kernel's output on this frame (so agreeing
    with the tensor walk tests it)."""
    gb = with_backface(FRAMES["rough"](), depth=0.05)
    with torch.no_grad():
        run = lambda **o: BitmaskAO(slices=3, steps=4, backend="kernel", trainable=False, **o)(gb).visibility  # noqa: E731
        plain = run()
        assert (run(fetch="edge_aware") - plain).abs().max() > 0.01
        assert (run(thickness=BackfaceThickness()) - plain).abs().max() > 0.01


def test_coverage_reasons():
    gb = with_backface(FRAMES["example"]())
    position = type(gb)(depth=gb.depth, camera=gb.camera, position=gb.positions(), backface_depth=gb.backface_depth)
    with torch.no_grad():
        assert kernel_covers(BitmaskAO(fetch="edge_aware", trainable=False), gb) is None
        assert kernel_covers(BitmaskAO(fetch="edge_aware", trainable=False), position) is None  # (no gradient)
        glsl = BitmaskAO(variant="ssilvb_glsl", thickness=BackfaceThickness(), trainable=False)
        assert kernel_covers(glsl, gb) is None  # (the shader's hitThickness read at each sample's texel)

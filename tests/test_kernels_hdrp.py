"""The hard kernel of bitmask AO's ``"hdrp"`` variant (bitmask.h's BitmaskAccumulator with HDRP's angles: the
slice frame of ``HDRPAccumulator.slice_frame``, the 3D cosines through ``fast_acos``, the ``yx`` swap) against the
tensor-op walk, by the tolerance of tests/kernel_agreement.py, in SIMD and scalar lanes."""
import pytest
import torch

from kernel_agreement import assert_masks_agree, assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture)
from test_kernels_exact import with_backface
from test_kernels_glsl import lit
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import kernel_covers
from torch_ao.kernels.bitmask import bitmask_outputs, module_thickness, thickness_options
from torch_ao.methods.bitmask import SSILVB, BitmaskAO
from torch_ao.thickness import BackfaceThickness

# (the variant's slices default to screen directions; without jitter those are the image's axes, whose samples lie
# within rounding of a texel row, where either path's rounding picks the row: that setting walks view directions)
SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=6, radius=0.6, thickness=0.2),
    dict(slices=2, steps=5, jitter=False, azimuth="view", rounding="round", step_power=2.0, min_step_px=2.0),
    dict(slices=3, steps=3, fetch="nearest", border="clamp", rounding="floor", seed=3),
    dict(slices=2, steps=4, border="clamp", thickness=3.0, sector_epsilon=0.01),
    dict(slices=3, steps=4, noise="hilbert_r2", stagger=True, seed=2, fetch="edge_aware"),
    dict(slices=3, steps=4, thickness=BackfaceThickness(scale=0.8, thickness=0.05)),
]


def kernel_of(module: BitmaskAO, gb: GBuffer, lanes: str = "simd"):
    return bitmask_outputs(gb, gb.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                           radius=float(module.radius), **thickness_options(module_thickness(module, gb)),
                           step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                           seed=module.seed, noise=module.noise, stagger=module.stagger, fetch=module.fetch,
                           border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon,
                           weighting=module.weighting, indirect=module.want_indirect, bent_normals=module.want_bent,
                           variant=module.variant, azimuth=module.azimuth, lanes=lanes)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_hdrp_masks_agree_with_the_tensor_walk(built, frame, setting, lanes):
    """Against the float32 tensor walk (on planar frames the float64 one decides samples on the pixel's own plane
    by its own rounding: kernel_agreement.degenerate). Where the kernel's mask is not the float32 walk's it is the
    float64 walk's: the kernel rounds the slice angle as float64 does (bitmask.h's hdrp_slice_angle takes
    ``fast_acos``' root from the slice's sine), which moves the hemisphere's edge on up to 2 of the crease frame's
    1600 pixels (share 0.998; 0 to 2 pixels on every frame)."""
    gb = with_backface(FRAMES[frame]())
    module = BitmaskAO(variant="hdrp", mode="hard", backend="torch", trainable=False, **SETTINGS[setting])
    with torch.no_grad():
        reference = module(gb).visibility
        float64 = module.double()(gb.to(dtype=torch.float64)).visibility
        assert kernel_covers(module.float(), gb) is None
        out = kernel_of(module.float(), gb, lanes).visibility
    assert reference.min() < 1  # something is occluded: the comparison means something
    differ = (out != reference) & gb.valid
    assert torch.allclose(out[differ].double(), float64[differ], atol=1e-6, rtol=0)
    assert_masks_agree(out, reference, gb.valid, module.slices, share=0.998)


@pytest.mark.parametrize("weighting", ["uniform", "cosine"])
@pytest.mark.parametrize("frame", ["example", "rough", "crease"])
@pytest.mark.parametrize("setting", [0, 3, 6])
def test_hdrp_indirect_light_bent_normals_and_ambient_agree(built, weighting, frame, setting):
    """Every output of the module through the kernel (``backend="kernel"``) and the scalar lanes, by tolerance,
    against the float64 tensor walk. HDRP's slice angle ``fast_acos(cos_n)`` has an unbounded slope in ``cos_n`` where
    the normal faces the view vector (``sqrt(1 - cos_n)``): the float32 tensor walk's rounding of ``cos_n`` there turns
    the sector centres (its bent normals up to 0.03 off on the crease frame), the kernel's root from the slice's sine
    does not (bitmask.h's hdrp_slice_angle)."""
    front = with_backface(FRAMES[frame]())
    gb = GBuffer(depth=front.depth, camera=front.camera, normals=front.normals, backface_depth=front.backface_depth,
                 light=lit(front).light)
    options = dict(variant="hdrp", mode="hard", trainable=False, weighting=weighting, indirect=True, bent_normals=True,
                   ambient=(0.2, 0.5, 1.0), **SETTINGS[setting])
    with torch.no_grad():
        ref = BitmaskAO(backend="torch", **options).double()(gb.to(dtype=torch.float64))
        out = BitmaskAO(backend="kernel", **options)(gb)
        scalar = kernel_of(BitmaskAO(**options), gb, "scalar")
    assert ref.indirect.max() > 0.01 and ref.visibility.min() < 1
    for lanes in (out, scalar):
        for name in ("visibility", "indirect", "bent_normal"):
            assert_values_agree(getattr(lanes, name).double(), getattr(ref, name), gb.valid, bound=0.2)
    assert_values_agree(out.ambient.double(), ref.ambient, gb.valid, bound=0.2)


def test_the_variant_and_its_screen_directions_change_the_kernels_output(built):
    """HDRP's rule is not the default one, on the same walk; and its default screen directions are walked (so
    agreeing with the tensor walk above tests both)."""
    gb = FRAMES["rough"]()
    with torch.no_grad():
        run = lambda **o: BitmaskAO(slices=3, steps=4, backend="kernel", trainable=False, **o)(gb)  # noqa: E731
        hdrp = run(variant="hdrp", weighting="cosine", bent_normals=True)
        plain = run(variant="default", azimuth="view", sector_epsilon=0.0, weighting="cosine", bent_normals=True)
        view = run(variant="hdrp", azimuth="view", weighting="cosine", bent_normals=True)
    for other in (plain, view):
        assert (hdrp.visibility - other.visibility).abs().max() > 0.01
        assert (hdrp.bent_normal - other.bent_normal).abs().max() > 0.01


def test_auto_backend_takes_the_kernel(built, monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    calls = []
    for name in ("bitmask_hard", "bitmask_outputs"):
        real = getattr(dispatch, name)
        monkeypatch.setattr(dispatch, name, lambda *a, _real=real, **k: calls.append(k["variant"]) or _real(*a, **k))
    gb = lit(FRAMES["rough"]())
    # autograd on, trainable parameters: uniform hard masks have no gradient
    auto = BitmaskAO(variant="hdrp", slices=3, steps=4)(gb)
    assert calls == ["hdrp"]
    with torch.no_grad():
        reference = BitmaskAO(variant="hdrp", slices=3, steps=4, backend="torch")(gb)
    assert_masks_agree(auto.visibility, reference.visibility, gb.valid, 3)
    # indirect light has a gradient (the radius, the light): the kernel's backward (tests/test_kernels_hdrp_grad.py)
    light = SSILVB(variant="hdrp", slices=3, steps=4)
    assert kernel_covers(light, gb) is None
    out = light(gb)
    assert calls == ["hdrp", "hdrp"] and out.indirect.requires_grad


def test_coverage_reasons():
    gb = lit(FRAMES["example"]())
    with torch.no_grad():
        assert kernel_covers(BitmaskAO(variant="hdrp", weighting="cosine", bent_normals=True, ambient=0.5), gb) is None
        assert kernel_covers(BitmaskAO(variant="hdrp", fetch="edge_aware", thickness=BackfaceThickness()),
                             with_backface(gb)) is None
        # a straight-through forward without a gradient is the hard masks' (its gradients: the soft kernel's,
        # tests/test_kernels_soft_hdrp.py)
        assert kernel_covers(BitmaskAO(variant="hdrp", mode="straight_through", bent_normals=True), gb) is None
        assert "union" in kernel_covers(BitmaskAO(variant="hdrp", union="exact"), gb)
        assert kernel_covers(BitmaskAO(variant="hdrp", thickness_growth=0.5), gb) is None
        positions = GBuffer(depth=None, camera=gb.camera, position=gb.positions())
        assert kernel_covers(BitmaskAO(variant="hdrp"), positions) is None  # (no gradient: its taps interpolated)
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera, light=gb.light)
    for graded in (dict(), dict(weighting="cosine"), dict(bent_normals=True), dict(indirect=True)):
        assert kernel_covers(BitmaskAO(variant="hdrp", **graded), graph) is None  # (gradients: its backward)
    with pytest.raises(ValueError, match="variant: expected one of"):
        bitmask_outputs(gb, gb.view_normals(), slices=2, steps=3, radius=1.0, thickness=0.5, variant="ssilvb_glsl")

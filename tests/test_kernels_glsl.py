"""The hard bitmask kernels beyond uniform visibility against the tensor-op walk: cosine sector weights,
indirect light, bent normals and ambient light of the ``"default"`` variant, and the ``"ssilvb_glsl"``
variant (AO and indirect light, with the GLSL step placement and accumulator), all on the one walk and by
the tolerance of tests/kernel_agreement.py, on the frames and settings of tests/test_kernels.py; and the
kernel against the SSILVB GLSL article's shader on Mesa (as tests/test_glsl_parity.py checks the tensor
path)."""
import shutil

import pytest
import torch

from test_kernels import FRAMES, SETTINGS, built, rough_gbuffer  # noqa: F401  (built: the fixture)
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import bitmask_outputs, kernel_covers, ssilvb_glsl_hard
from torch_ao.methods.bitmask import SSILVB, BitmaskAO

from kernel_agreement import SHARE, assert_masks_agree, assert_values_agree, degenerate

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="the kernels need a C++ compiler")


def lit(gb: GBuffer, seed: int = 1) -> GBuffer:
    """``gb`` with a random direct-light buffer (the light is only gathered, so any values test it)."""
    g = torch.Generator().manual_seed(seed)
    light = torch.rand(gb.depth.shape[0], 3, *gb.depth.shape[-2:], generator=g)
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=light)


def both(gb: GBuffer, **options):
    """The module's outputs through the tensor path and through the kernel (no autograd)."""
    with torch.no_grad():
        return (BitmaskAO(mode="hard", backend="torch", **options)(gb),
                BitmaskAO(mode="hard", backend="kernel", **options)(gb))


def assert_identical(out, ref, name):
    assert out.shape == ref.shape and out.dtype == ref.dtype, name
    assert torch.equal(out, ref), (name, (out != ref).sum().item(), (out - ref).abs().max().item())


# ------------------------------------------------------------------------------- the default variant
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_cosine_weighted_visibility_agrees(built, frame, setting):
    gb = FRAMES[frame]()
    ref, out = both(gb, weighting="cosine", **SETTINGS[setting])
    assert ref.visibility.min() < 1
    # the weights are not 1/32: cosine visibility differs from the uniform one where something is occluded
    uniform, _ = both(gb, **SETTINGS[setting])
    assert not torch.equal(ref.visibility, uniform.visibility)
    # one sector of one slice flipped moves at most that sector's share of the cosine weights
    share = 0.0 if frame != "rough" and degenerate(SETTINGS[setting]) else SHARE
    assert_values_agree(out.visibility, ref.visibility, gb.valid, bound=0.1 / SETTINGS[setting]["slices"], share=share)


@pytest.mark.parametrize("weighting", ["uniform", "cosine"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", [0, 1, 3])
def test_indirect_light_bent_normals_and_ambient(built, weighting, frame, setting):
    """Every output, by tolerance (the ambient light is the visibility times the colour)."""
    gb = lit(FRAMES[frame]())
    ref, out = both(gb, weighting=weighting, indirect=True, bent_normals=True, ambient=(0.2, 0.5, 1.0),
                    **SETTINGS[setting])
    assert ref.indirect.max() > 0.01 and ref.visibility.min() < 1
    for name in ("visibility", "indirect", "bent_normal", "ambient"):
        assert_values_agree(getattr(out, name), getattr(ref, name), gb.valid, bound=0.2)


def test_bent_normals_point_away_from_the_occluder_and_background_keeps_its_normal(built):
    gb = lit(rough_gbuffer())
    normals = gb.view_normals()
    out = bitmask_outputs(gb, normals, slices=4, steps=6, radius=1.0, thickness=0.5, bent_normals=True,
                          indirect=True, weighting="cosine")
    bent = out.bent_normal
    assert torch.allclose(bent.norm(dim=1), torch.ones_like(bent[:, 0]), atol=1e-5)
    background = ~gb.valid.expand_as(bent)
    assert torch.equal(bent[background], normals[background])
    assert torch.equal(out.indirect[background], torch.zeros_like(out.indirect[background]))
    # a fully visible pixel's bent normal is its normal (within the sector quantisation)
    visible = (out.visibility > 0.999).expand_as(bent) & ~background
    assert visible.any() and (bent - normals)[visible].abs().max() < 0.05


def test_chunked_calls_agree_with_the_chunked_tensor_path(built):
    """A frame the tensor path walks in several chunks (the module's ``chunk_size``): the kernel walks it whole."""
    gb = FRAMES["rough"]()
    ref, out = both(gb, weighting="cosine", slices=3, steps=5, chunk_size=1000)
    assert_values_agree(out.visibility, ref.visibility, gb.valid, bound=0.1 / 3)


def test_the_fit_pipeline_scores_through_the_kernel(built, monkeypatch):
    """``torch-ao fit`` scores ``BitmaskAO(preset="high", weighting="cosine")`` in hard mode without
    autograd: that call runs the kernel, with the tensor path's numbers."""
    import torch_ao.kernels.dispatch as dispatch

    calls = []
    real = dispatch.bitmask_hard
    monkeypatch.setattr(dispatch, "bitmask_hard", lambda *a, **k: calls.append(k["weighting"]) or real(*a, **k))
    gb = FRAMES["example"]()
    module = BitmaskAO(preset="high", weighting="cosine")
    with torch.no_grad():
        out = module(gb).visibility
    assert calls == ["cosine"]
    with torch.no_grad():
        assert_values_agree(out, BitmaskAO(preset="high", weighting="cosine", backend="torch")(gb).visibility, gb.valid,
                            bound=0.1 / module.slices)


def test_coverage_of_the_new_outputs():
    gb = lit(FRAMES["example"]())
    everything = BitmaskAO(weighting="cosine", indirect=True, bent_normals=True, ambient=0.5)
    with torch.no_grad():
        assert kernel_covers(everything, gb) is None
    # the light's factors move with the radius (the sample positions): a trainable radius has a gradient, which the
    # hard kernel's backward gives (Euler's identity)
    assert kernel_covers(everything, gb) is None
    assert kernel_covers(BitmaskAO(weighting="cosine", bent_normals=True), gb) is None  # (not with the radius)
    assert kernel_covers(SSILVB(variant="ssilvb_glsl"), gb) is None  # the shader's radius only picks texels
    assert "ambient" in kernel_covers(BitmaskAO(ambient=lambda d: d), gb)
    assert "straight-through gradient" in kernel_covers(SSILVB(variant="ssilvb_glsl", mode="straight_through"), gb)
    # gradients the hard outputs do have, through the normals (cosine weights) and the light: the hard kernel's
    # backward (the shader's light: tests/test_kernels_glsl_grad.py)
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera, light=gb.light)
    assert kernel_covers(BitmaskAO(weighting="cosine", bent_normals=True), graph) is None
    assert kernel_covers(SSILVB(weighting="cosine"), graph) is None
    assert kernel_covers(BitmaskAO(), graph) is None  # uniform hard visibility has none
    light = GBuffer(depth=gb.depth, camera=gb.camera, light=gb.light.clone().requires_grad_())
    assert kernel_covers(SSILVB(variant="ssilvb_glsl"), light) is None  # (the shader's light: its own backward)
    assert kernel_covers(BitmaskAO(variant="ssilvb_glsl"), light) is None  # AO only: no gradient
    with torch.no_grad():
        assert kernel_covers(SSILVB(variant="ssilvb_glsl"), light) is None
    positions = GBuffer(depth=None, camera=gb.camera, position=gb.positions().requires_grad_())
    assert kernel_covers(BitmaskAO(weighting="cosine"), positions) is None  # (its gradient: the four taps')


def test_indirect_light_without_a_light_buffer_is_refused_by_name(built):
    gb = FRAMES["example"]()
    gb = GBuffer(depth=gb.depth, camera=gb.camera)
    with pytest.raises(ValueError, match="gbuffer.light"):
        with torch.no_grad():
            SSILVB(backend="kernel")(gb)


# ------------------------------------------------------------------------------- ssilvb_glsl
GLSL_SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=6, radius=0.6, thickness=0.2),
    dict(slices=2, steps=5, jitter=False, rounding="round"),
    dict(slices=5, steps=3, radius=2.0, rounding="floor", thickness=0.0),
]


def assert_glsl_agrees(out, ref, valid, slices):
    """The ``"ssilvb_glsl"`` kernel's outputs against the tensor walk's: hard masks identical on >= 99.9 % of
    the pixels and one sector apart at most; that sector stays in the shader's mask (never reset) for the
    later slices, so visibility is at most ``sliceCount + 1`` sectors of one slice apart. The light within
    1e-5 on >= 99.9 % of the pixels."""
    assert_masks_agree(out.visibility, ref.visibility, valid, slices, sectors=slices + 1)
    assert_values_agree(out.indirect, ref.indirect, valid, bound=0.2)


@pytest.mark.parametrize("numerics", ["ieee", "mesa", "mesa_mediump"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(GLSL_SETTINGS)))
def test_ssilvb_glsl_agrees_with_the_tensor_walk(built, numerics, frame, setting):
    """In both lane types: the SIMD lanes (what the module runs) and the scalar ones (the CUDA build's)."""
    gb = lit(FRAMES[frame]())
    options = dict(variant="ssilvb_glsl", indirect=True, glsl_numerics=numerics, **GLSL_SETTINGS[setting])
    ref, out = both(gb, **options)
    assert ref.indirect.max() > 0  # (visibility may be one value everywhere: the shader's quirks, e.g. 1.2 with 5 slices)
    module = BitmaskAO(mode="hard", **options)
    assert_glsl_agrees(out, ref, gb.valid, module.slices)
    scalar = ssilvb_glsl_hard(gb, gb.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                              radius=module.radius, thickness=float(module.thickness.detach()), jitter=module.jitter,
                              rounding=module.rounding, numerics=numerics, indirect=True, lanes="scalar")
    assert_glsl_agrees(scalar, ref, gb.valid, module.slices)
    ao_only, _ = both(gb, **dict(options, indirect=False))
    assert_identical(ao_only.visibility, out.visibility, "visibility without light")


def test_ssilvb_glsl_batch_images_are_independent(built):
    gb = lit(rough_gbuffer())
    normals = gb.view_normals()
    out = ssilvb_glsl_hard(gb, normals, slices=3, steps=4, radius=1.0, thickness=0.3, indirect=True)
    one = GBuffer(depth=gb.depth[1:], camera=type(gb.camera)(gb.camera.intrinsics[1:], gb.camera.height, gb.camera.width),
                  light=gb.light[1:])
    single = ssilvb_glsl_hard(one, normals[1:], slices=3, steps=4, radius=1.0, thickness=0.3, indirect=True)
    assert torch.equal(single.visibility, out.visibility[1:]) and torch.equal(single.indirect, out.indirect[1:])
    assert torch.equal(out.visibility[~gb.valid], torch.ones_like(out.visibility[~gb.valid]))


@pytest.mark.gl
@pytest.mark.slow
def test_ssilvb_glsl_kernel_matches_the_shader_on_mesa_softpipe(built, tmp_path):
    """The kernel against the shader, with the thresholds tests/test_glsl_parity.py sets for the tensor path
    (every pixel whose walk never fetches its own texel: visibility bit for bit on >= 97 % per case and
    99 % overall, light within 1e-5), and agreeing with the tensor path (assert_glsl_agrees)."""
    import sys

    import test_glsl_parity as parity

    sys.path.insert(0, str(parity.HERE / "glsl"))
    from runner import centre_texel_pixels

    rendered = parity._render("softpipe", tmp_path)
    exact, total = 0.0, 0
    for name in parity.SCENES:
        gb = parity.scene(name)
        for i, (sl, st, r, t, jit) in enumerate(parity.SETTINGS):
            gl = rendered[f"{name}/{i}"]
            ref, out = both(gb, variant="ssilvb_glsl", indirect=True, slices=sl, steps=st, radius=r, thickness=t,
                            jitter=jit, glsl_numerics="mesa")
            assert_glsl_agrees(out, ref, gb.valid, sl)
            ok = ~centre_texel_pixels(gb, slices=sl, steps=st, radius=r, jitter=jit, numerics="mesa")
            dv = (out.visibility[0, 0] - gl[..., 3]).abs()
            di = (out.indirect[0].permute(1, 2, 0) - gl[..., :3]).abs().amax(-1)
            share = float((dv[ok] == 0).float().mean())
            assert share >= 0.97, (name, i, share)
            assert float(di[ok & (dv == 0)].max()) < 1e-5, (name, i)
            exact, total = exact + share * int(ok.sum()), total + int(ok.sum())
    assert exact / total >= 0.99


@pytest.mark.slow
def test_an_engine_sized_frame_walked_in_chunks(built):
    """640x360: the tensor path walks 16384-pixel chunks, the kernel the whole frame."""
    from torch_ao.examples import example_gbuffer

    gb = example_gbuffer(360, 640)
    ref, out = both(gb, weighting="cosine", bent_normals=True, slices=3, steps=3)
    assert BitmaskAO(weighting="cosine").chunking(gb)[0] == 16384
    assert_values_agree(out.visibility, ref.visibility, gb.valid, bound=0.1 / 3)
    assert_values_agree(out.bent_normal, ref.bent_normal, gb.valid, bound=0.2)
    with torch.no_grad():
        lit_ref, lit_out = SSILVB(backend="torch", slices=2, steps=16)(gb), SSILVB(backend="kernel", slices=2, steps=16)(gb)
    assert_values_agree(lit_out.indirect, lit_ref.indirect, gb.valid, bound=0.2)
    with torch.no_grad():
        options = dict(variant="ssilvb_glsl", slices=4, steps=8, glsl_numerics="mesa")
        glsl_ref, glsl = SSILVB(backend="torch", **options)(gb), SSILVB(backend="kernel", **options)(gb)
    assert_glsl_agrees(glsl, glsl_ref, gb.valid, 4)


@pytest.mark.parametrize("fetch, border", [("edge_aware", "drop"), ("bilinear", "clamp"), ("nearest", "drop")])
def test_the_shaders_own_texel_fetch_whatever_fetch_and_border_say(built, fetch, border):
    """The shader reads each sample's nearest texel, clamped to the image, whatever the module's ``fetch`` and
    ``border`` (GLSLPattern's own): the kernel covers every such call and gives what it gives with the defaults,
    which equals the tensor path's with these options."""
    gb = lit(FRAMES["rough"]())
    with torch.no_grad():
        module = SSILVB(variant="ssilvb_glsl", fetch=fetch, border=border, backend="kernel")
        assert kernel_covers(module, gb) is None
        out = module(gb)
        default = SSILVB(variant="ssilvb_glsl", backend="kernel")(gb)
        ref = SSILVB(variant="ssilvb_glsl", fetch=fetch, border=border, backend="torch")(gb)
    assert ref.visibility.min() < 0.9 and ref.indirect.max() > 0.01
    for name in ("visibility", "indirect"):
        assert_identical(getattr(out, name), getattr(default, name), name)
    assert_values_agree(torch.cat([out.visibility, out.indirect], 1), torch.cat([ref.visibility, ref.indirect], 1),
                        gb.valid, atol=1e-5, bound=1e-5)


@pytest.mark.parametrize("variant, options", [("default", dict(weighting="cosine", bent_normals=True, ambient=0.5)),
                                              ("hdrp", dict(weighting="uniform", bent_normals=True)),
                                              ("ssilvb_glsl", dict())])
def test_straight_through_without_a_gradient_is_hard_mode(built, variant, options, monkeypatch):
    """Straight-through mode's values are hard mode's (its soft union only shapes gradients): without a gradient
    the hard kernel computes every output of every variant, equal to its hard-mode call's and to the tensor path's
    straight-through call by the hard kernels' tolerance."""
    from kernel_calls import count_kernel_calls

    gb = lit(FRAMES["rough"]())
    with torch.no_grad():
        module = SSILVB(variant=variant, mode="straight_through", backend="kernel", **options)
        assert kernel_covers(module, gb) is None
        out = module(gb)
        hard = SSILVB(variant=variant, mode="hard", backend="kernel", **options)(gb)
        # (the float64 walk but for the shader, whose numbers are float32's: hdrp's float32 slice angle is off where
        # the normal faces the view vector, tests/test_kernels_hdrp.py)
        dtype = torch.float32 if variant == "ssilvb_glsl" else torch.float64
        ref = SSILVB(variant=variant, mode="straight_through", backend="torch", **options).to(dtype)(gb.to(dtype=dtype))
    names = [n for n in ("visibility", "indirect", "bent_normal", "ambient") if getattr(ref, n) is not None]
    for name in names:
        assert_identical(getattr(out, name), getattr(hard, name), name)
    if variant == "ssilvb_glsl":
        assert_glsl_agrees(out, ref, gb.valid, module.slices)
    else:
        assert_values_agree(torch.cat([getattr(out, n) for n in names], 1).double(),
                            torch.cat([getattr(ref, n) for n in names], 1), gb.valid, bound=0.2)
    # with a gradient asked for, straight-through mode's own (soft) gradients: not the hard kernel's
    calls = count_kernel_calls(monkeypatch, "bitmask")
    assert "straight-through gradient" in kernel_covers(SSILVB(variant=variant, mode="straight_through", **options), gb)
    assert calls == []

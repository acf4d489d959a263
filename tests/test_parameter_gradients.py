"""Every registered ``nn.Parameter`` of every method gets a finite, nonzero gradient at its default in
the differentiable mode on a small frame (a default without one would be skipped by an optimizer
without a word: such a value is a buffer, see GTAO's ``falloff_range``)."""
import inspect
import math
import pydoc

import pytest
import torch

from torch_ao.examples import example_gbuffer
from torch_ao.methods import METHODS, get_method

#: Each method's differentiable configuration: bitmask AO's soft masks, SSAO's and UE4 SSAO's logistic
#: comparisons instead of the published hard steps.
DIFFERENTIABLE = {"mode": "soft", "softness": 0.01, "flat_softness": 0.01}

#: (method, variant, parameter) that get no gradient at the published defaults, and so are buffers there.
NO_GRADIENT = {("ssao", None, "bias"), ("ue4_ssao", None, "radius"), ("ue4_ssao", None, "flat_surface_bias"),
               ("gtao", "exact", "falloff_range"), ("bitmask", "ssilvb_glsl", "radius"),
               ("ssilvb", "ssilvb_glsl", "radius")}


def _cases():
    for name in METHODS:
        cls = get_method(name)
        variant = cls.options().get("variant")
        for v in (variant.choices if variant else (None,)):
            yield name, v


def _module(name, variant, **extra):
    cls = get_method(name)
    options = cls.options()
    kw = {"slices": 2, "steps": 2} if "slices" in options else {"preset": "low"}
    kw |= {"variant": variant} if variant else {}
    kw |= {"union": "sectors"} if (name, variant) == ("ssilvb", "exact") else {}  # indirect light needs sectors
    kw |= {"jitter": False} if "jitter" in options else {}
    return cls(**kw, **{k: v for k, v in extra.items() if k in options})


@pytest.mark.parametrize("name, variant", list(_cases()))
def test_every_parameter_gets_a_gradient_at_its_default(name, variant):
    module = _module(name, variant, **DIFFERENTIABLE)
    out = module(example_gbuffer(12, 16))
    loss = out.visibility.sum() + (out.indirect.sum() if out.indirect is not None else 0)
    params = dict(module.named_parameters())
    assert params, "no parameter to fit"
    grads = dict(zip(params, torch.autograd.grad(loss, list(params.values()), allow_unused=True)))
    for key, grad in grads.items():
        assert grad is not None and bool(torch.isfinite(grad).all()) and bool((grad != 0).any()), (key, grad)


@pytest.mark.parametrize("name, variant", list(_cases()))
def test_parameters_without_a_gradient_at_the_published_default_are_buffers(name, variant):
    module = _module(name, variant)
    expected = {key for n, v, key in NO_GRADIENT if (n, v) == (name, variant)}
    assert set(module.no_gradient_options) == expected
    params, buffers = dict(module.named_parameters()), dict(module.named_buffers())
    assert not expected & set(params) and expected <= set(buffers)


def test_no_gradient_parameters_become_parameters_in_the_differentiable_configuration():
    from torch_ao import SSAO, UE4SSAO, BitmaskAO

    assert {"radius", "bias"} <= dict(SSAO(softness=0.01).named_parameters()).keys()
    assert {"radius", "flat_surface_bias"} <= dict(UE4SSAO(flat_softness=0.01, fetch="bilinear").named_parameters()).keys()
    assert "radius" in dict(BitmaskAO(variant="default").named_parameters())
    assert "radius" in dict(BitmaskAO(variant="ssilvb_glsl", trainable=True).named_buffers())


def test_ssao_radius_keeps_the_range_check_gradient_with_the_hard_step():
    """With the published hard step SSAO's radius still shapes the result through LearnOpenGL's range check
    (occluders more than a radius in front fade out), so it stays a parameter."""
    module = get_method("ssao")(jitter=False)
    (grad,) = torch.autograd.grad(module(example_gbuffer(12, 16)).visibility.sum(), [module.radius])
    assert float(grad) != 0 and math.isfinite(float(grad))


@pytest.mark.slow
def test_fit_names_why_a_parameter_is_not_fittable(tmp_path, capsys):
    from torch_ao.cli import main

    code = main(["fit", "--method", "ssao", "--params", "bias", "--size", "16x12", "--spp", "16", "--train-views", "1",
                 "--scenes", "sphere_on_plane", "--steps", "1", "--no-progress", "--cache", str(tmp_path / "cache"),
                 "--out", str(tmp_path / "fit")])
    assert code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "torch-ao fit: error: --params: 'bias' is not a fitted parameter of ssao with these options: the hard "
        "occlusion step (softness 0) has no gradient: give softness > 0 to fit it")
    assert not (tmp_path / "fit").exists()


@pytest.mark.parametrize("module, functional", [("SSAO", "ssao"), ("HBAO", "hbao"), ("UE4SSAO", "ue4_ssao"),
                                                ("GTAO", "gtao"), ("PSSAO", "pssao"), ("BitmaskAO", "bitmask_ao"),
                                                ("SSILVB", "ssilvb")])
def test_functional_signature_lists_the_module_options(module, functional):
    import torch_ao

    cls, fn = getattr(torch_ao, module), getattr(torch_ao, functional)
    sig, module_sig = inspect.signature(fn), inspect.signature(cls)
    assert list(sig.parameters) == ["gbuffer", *module_sig.parameters]
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in module_sig.parameters.values())  # no **kwargs
    python_only = {"ambient"} if module in ("BitmaskAO", "SSILVB") else set()  # a callable: no CLI flag
    assert set(module_sig.parameters) == set(cls.options()) | python_only
    for name in module_sig.parameters:
        p = sig.parameters[name]
        assert p.kind is inspect.Parameter.KEYWORD_ONLY
        assert p.default == (False if name == "trainable" else module_sig.parameters[name].default), name
    assert "Shape:" in fn.__doc__
    # help() shows them
    listed = lambda params: ", ".join(str(p) for p in params)  # noqa: E731
    assert f"{functional}(gbuffer, *, {listed(list(sig.parameters.values())[1:])})" in pydoc.render_doc(fn, renderer=pydoc.plaintext)
    assert f"__init__(self, *, {listed(module_sig.parameters.values())})" in pydoc.render_doc(cls, renderer=pydoc.plaintext)


@pytest.mark.parametrize("cls_name, variant", [("BitmaskAO", "default"), ("BitmaskAO", "exact"), ("BitmaskAO", "hdrp"),
                                               ("SSILVB", "default")])
def test_bitmask_signature_defaults_are_the_constructor_defaults(cls_name, variant):
    """Every default the signature shows, passed explicitly, builds the module the bare call builds."""
    import torch_ao

    cls = getattr(torch_ao, cls_name)
    shown = {n: p.default for n, p in inspect.signature(cls).parameters.items()}
    a = cls(**(shown | {"variant": variant, "slices": 2, "steps": 2, "jitter": False}))
    b = cls(variant=variant, slices=2, steps=2, jitter=False)
    assert repr(a) == repr(b) and a.sampling == b.sampling and a._auto_chunk == b._auto_chunk
    g = example_gbuffer(12, 16)  # (lit: SSILVB has its light)
    oa, ob = a(g), b(g)
    assert torch.equal(oa.visibility, ob.visibility)
    if cls_name == "SSILVB":
        assert torch.equal(oa.indirect, ob.indirect)


"""The public API documents its shapes: every export that takes or returns images has a kornia-style
``Shape:`` section."""
import inspect


#: what torch_ao exports that neither takes nor returns images (registries, a name lookup, fit's settings)
NO_IMAGES = {"METHODS", "PRESETS", "get_method", "FitConfig"}


def test_every_public_api_on_images_has_a_shape_section():
    import re

    import torch_ao

    for name in torch_ao.__all__:
        if name in NO_IMAGES:
            continue
        doc = inspect.getdoc(getattr(torch_ao, name)) or ""
        assert "\nShape:\n" in doc, name
        section = doc.split("\nShape:\n", 1)[1]
        assert re.search(r"\(B, [13C], H, W\)", section), name  # kornia style, batch first

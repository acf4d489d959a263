"""The documentation site (mkdocs.yml): every page of docs/ is in its navigation, and its API page
documents every name of ``torch_ao.__all__`` (``.ci/run`` builds it with ``mkdocs build --strict``)."""
import importlib
import re
from pathlib import Path

import torch_ao

ROOT = Path(__file__).resolve().parent.parent


def test_every_page_is_in_the_navigation():
    nav = re.findall(r":\s*([\w./-]+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), flags=re.M)
    pages = sorted(p.name for p in (ROOT / "docs").glob("*.md"))
    assert sorted(nav) == pages


def test_the_api_page_documents_all_of_torch_ao():
    documented = re.findall(r"^::: torch_ao\.([\w.]+)$", (ROOT / "docs" / "api.md").read_text(), flags=re.M)
    # ``fit`` and ``denoise`` are also submodules' names, so the page names them by their defining module.
    names = [name.rsplit(".", 1)[-1] for name in documented]
    assert sorted(names) == sorted(torch_ao.__all__)
    for path in documented:
        module, _, name = f"torch_ao.{path}".rpartition(".")
        assert getattr(importlib.import_module(module), name) is getattr(torch_ao, name), path

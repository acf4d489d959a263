"""The kernel library's build cache: a current build is loaded without running cpp_extension (ninja),
and any change of what it was built from (a source, a header beside it, a flag, a deleted library)
builds it again. cpp_extension.load and torch.ops.load_library are replaced by recorders, so no
compiler runs here; the real build and load are covered by the kernel tests."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch.utils import cpp_extension

from torch_ao.kernels import build


@pytest.fixture
def recorder(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    calls = {"build": [], "load": []}

    def fake_build(name, sources, extra_cflags, extra_ldflags, is_python_module, build_directory, verbose):
        assert not is_python_module
        library = Path(build_directory) / f"{name}{cpp_extension.LIB_EXT}"
        library.write_bytes(b"".join(Path(s).read_bytes() for s in sources))
        calls["build"].append((list(sources), list(extra_cflags)))
        return str(library)

    monkeypatch.setattr(cpp_extension, "load", fake_build)
    monkeypatch.setattr(torch.ops, "load_library", lambda path: calls["load"].append(path))
    source = tmp_path / "src" / "k.cpp"
    source.parent.mkdir()
    source.write_text("int f() { return 1; }\n")
    return calls, source


def test_current_build_is_loaded_without_building(recorder):
    calls, source = recorder
    first = build.load_cached_library("k_test", [source], ["-O3"], ["-fopenmp"])
    assert len(calls["build"]) == 1 and calls["load"] == []
    second = build.load_cached_library("k_test", [source], ["-O3"], ["-fopenmp"])
    assert len(calls["build"]) == 1, "an unchanged build ran cpp_extension again"
    assert calls["load"] == [str(first)] and second == first
    assert first.read_text() == source.read_text()


@pytest.mark.parametrize("change", ["source", "header", "cflags", "ldflags", "library deleted", "stamp corrupt"])
def test_any_change_rebuilds(recorder, change):
    calls, source = recorder
    cflags, ldflags = ["-O3"], ["-fopenmp"]
    library = build.load_cached_library("k_test", [source], cflags, ldflags)
    if change == "source":
        source.write_text("int f() { return 2; }\n")
    elif change == "header":
        (source.parent / "k.h").write_text("#define X 1\n")
    elif change == "cflags":
        cflags = ["-O2"]
    elif change == "ldflags":
        ldflags = []
    elif change == "library deleted":
        library.unlink()
    else:
        (library.parent / build._STAMP).write_text("garbage\n")
    again = build.load_cached_library("k_test", [source], cflags, ldflags)
    assert len(calls["build"]) == 2 and calls["load"] == []
    assert again.read_text() == source.read_text()
    build.load_cached_library("k_test", [source], cflags, ldflags)  # and now it is current again
    assert len(calls["build"]) == 2 and calls["load"] == [str(again)]

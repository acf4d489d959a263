"""The kernel library's build cache: a current build is loaded without running cpp_extension (ninja),
and any change of what it was built from (a source, a header beside it, a flag, a deleted library)
builds it again. cpp_extension.load and torch.ops.load_library are replaced by recorders, so no
compiler runs here; the real build and load are covered by the kernel tests."""
from __future__ import annotations

import ctypes
import locale
import sys
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


def test_a_build_whose_load_returns_none_is_found_and_stamped(recorder, monkeypatch):
    """torch 2.4's cpp_extension.load returns None for a library that is not a Python module (later releases return
    its path): the library is then the one cpp_extension names in the build folder, and a second process loads it."""
    calls, source = recorder
    real = cpp_extension.load
    monkeypatch.setattr(cpp_extension, "load", lambda **kw: real(**kw) and None)
    first = build.load_cached_library("k_test", [source], ["-O3"], [])
    assert first.name == f"k_test{cpp_extension.LIB_EXT}" and first.read_text() == source.read_text()
    assert build.load_cached_library("k_test", [source], ["-O3"], []) == first
    assert len(calls["build"]) == 1 and calls["load"] == [str(first)]


def test_kernel_sources_are_ascii():
    """NVRTC and the C++ compiler read the sources as bytes, and Python reads them (the CUDA source's assembly, the
    build's fingerprint) in whatever locale the process has: a library that a CUDA toolkit loads may switch it to
    C, whose codec is ASCII."""
    folder = Path(build.__file__).parent
    sources = [p for ext in ("*.h", "*.cpp", "*.cu") for p in folder.glob(ext)]
    assert len(sources) > 10
    for path in sources:
        text = path.read_bytes()
        assert text.isascii(), (path.name, text[:next(i for i, b in enumerate(text) if b > 127)][-80:])


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


def test_a_stale_torch_lock_is_removed_before_building(recorder, tmp_path, monkeypatch):
    """A build killed with SIGKILL leaves cpp_extension's ``lock`` file, on which every later build would
    wait forever: under the folder's own lock (whose holder is alive, or the OS released it) it is stale."""
    calls, source = recorder
    folder = Path(cpp_extension._get_build_directory("k_test", verbose=False))
    (folder / "lock").write_text("")
    seen = []
    fake = cpp_extension.load
    monkeypatch.setattr(cpp_extension, "load", lambda **kw: seen.append((folder / "lock").exists()) or fake(**kw))
    library = build.load_cached_library("k_test", [source], ["-O3"], [])
    assert seen == [False] and len(calls["build"]) == 1 and library.is_file()


LOCK_HOLDER = """
import fcntl, sys, time
from pathlib import Path
folder, stamp_text, library = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
with open(folder / "torch_ao_build.lock", "a") as handle:
    fcntl.flock(handle, fcntl.LOCK_EX)
    print("locked", flush=True)
    time.sleep(1.5)
    (folder / library).write_bytes(b"built by the other process")
    (folder / "torch_ao_build.sha256").write_text(stamp_text)
"""


def test_a_build_waits_for_a_live_builder_and_loads_what_it_built(recorder, tmp_path, capfd):
    import subprocess
    import sys
    import time

    calls, source = recorder
    folder = Path(cpp_extension._get_build_directory("k_test", verbose=False))
    name = f"k_test{cpp_extension.LIB_EXT}"
    stamp = f"{build._fingerprint([source], ['-O3'], [])} {name}\n"
    holder = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, str(folder), stamp, name], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "locked\n"
        start = time.perf_counter()
        library = build.load_cached_library("k_test", [source], ["-O3"], [])
        waited = time.perf_counter() - start
    finally:
        holder.wait(timeout=30)
    assert calls["build"] == [] and calls["load"] == [str(folder / name)] and library == folder / name
    assert waited > 0.5
    assert f"waiting for another process building the C++ kernels in {folder}" in capfd.readouterr().err


REAL_BUILD = """
import sys
from pathlib import Path
from torch_ao.kernels import build
print(build.load_cached_library("k_stale", [sys.argv[1]], [], []))
"""


@pytest.mark.slow
def test_a_real_build_completes_despite_a_stale_torch_lock(tmp_path):
    """cpp_extension itself (no recorder): a ``lock`` file left by a killed build does not hang the next one."""
    import os
    import subprocess
    import sys

    source = tmp_path / "k.cpp"
    source.write_text("extern \"C\" int torch_ao_stale_lock_test() { return 42; }\n")
    ext = tmp_path / "ext"
    (ext / "k_stale").mkdir(parents=True)
    (ext / "k_stale" / "lock").write_text("")
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(ext), PYTHONPATH=str(Path(build.__file__).parents[2]))
    proc = subprocess.run([sys.executable, "-c", REAL_BUILD, str(source)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    library = Path(proc.stdout.strip().splitlines()[-1])
    assert library.is_file() and library.parent == ext / "k_stale" and not (ext / "k_stale" / "lock").exists()


RETRY_AFTER_FAILURE = """
import sys
from pathlib import Path
from torch_ao.kernels import build
source = Path(sys.argv[1])
build.load_cached_library("k_retry", [source], [], [])  # a good build
source.write_text("extern \\"C\\" int torch_ao_retry_test() { return }\\n")  # then one that cannot compile
for attempt in range(2):  # (the second try in the same process must build again, not load the first build)
    try:
        build.load_cached_library("k_retry", [source], [], [])
        print("loaded")
    except RuntimeError:  # (cpp_extension's: the compiler's message)
        print("failed")
"""


@pytest.mark.slow
def test_a_retry_after_a_failed_build_builds_again(tmp_path):
    """cpp_extension itself: a build that fails, tried again in the same process, fails again; it does not load the
    library an earlier build left and record it as current (a later process would then load a stale library)."""
    import os
    import subprocess
    import sys

    source = tmp_path / "k.cpp"
    source.write_text("extern \"C\" int torch_ao_retry_test() { return 1; }\n")
    ext = tmp_path / "ext"
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(ext), PYTHONPATH=str(Path(build.__file__).parents[2]))
    proc = subprocess.run([sys.executable, "-c", RETRY_AFTER_FAILURE, str(source)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["failed", "failed"]
    assert not (ext / "k_retry" / build._STAMP).exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's newlocale and uselocale")
def test_a_thread_locale_switched_inside_the_nvrtc_guard_is_restored():
    """NVRTC 12.1 leaves the compiling thread in a "C" locale of its own, where Python's text files are ASCII; the
    guard around every NVRTC call (launch.thread_locale_kept) puts the thread's locale back."""
    from torch_ao.kernels.launch import thread_locale_kept

    libc = ctypes.CDLL(None)
    libc.newlocale.restype, libc.newlocale.argtypes = ctypes.c_void_p, [ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p]
    libc.uselocale.restype, libc.uselocale.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
    before = locale.getpreferredencoding(False)
    c_locale = libc.newlocale(1, b"C", None)  # (LC_CTYPE_MASK)
    with thread_locale_kept():
        libc.uselocale(c_locale)  # (as NVRTC 12.1 does)
        assert locale.getpreferredencoding(False) == "ANSI_X3.4-1968"
    assert locale.getpreferredencoding(False) == before
    libc.freelocale.argtypes = [ctypes.c_void_p]
    libc.freelocale(c_locale)

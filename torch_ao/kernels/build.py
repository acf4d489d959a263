"""Building the C++ kernels on first use (``torch.utils.cpp_extension``), cached per CPU capability."""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import sys
from pathlib import Path

import torch

__all__ = ["KernelUnavailable", "cpu_kernels", "grad_kernels", "load_cpu_library", "load_cached_library"]

#: the C++ sources of the one extension (registering its ops in ``torch_ao_kernels``): ops_cpu.cpp
#: compiles the one walk (walk.h and its accumulators)
_SOURCES = tuple(Path(__file__).with_name(name) for name in ("ops_cpu.cpp", "geometry_cpu.cpp"))

#: compiler flags per ``torch.backends.cpu.get_cpu_capability()``: the kernel's ``Vectorized<float>``
#: must be the width torch's own CPU kernels dispatch to, so that both call the same SLEEF functions
_CAPABILITY_FLAGS = {
    "AVX512": ["-mavx512f", "-mavx512bw", "-mavx512vl", "-mavx512dq", "-mfma", "-mf16c", "-DCPU_CAPABILITY=AVX512",
               "-DCPU_CAPABILITY_AVX512"],
    "AVX2": ["-mavx2", "-mfma", "-mf16c", "-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2"],
}


class KernelUnavailable(RuntimeError):
    """A kernel cannot run here (no C++ compiler, a failed build, an unsupported device)."""


def cpu_kernels():
    """The ``torch.ops.torch_ao_kernels`` namespace, building the C++ source on first use.

    Raises :class:`KernelUnavailable` when it cannot be built (the message says why). The build
    (about a minute, once per source version and CPU capability) is cached in
    ``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``).
    """
    _require("forwards")
    return torch.ops.torch_ao_kernels


def grad_kernels():
    """The namespace with the walk's backwards (``walk_backward``, ``soft_backward``, ``exact_backward``,
    ``hard_backward``; walk_grad_cpu.cpp), built on first use
    as a library of its own: its dual-number walk takes longer to compile than the forward kernels, and
    only calls that want gradients need it. Raises :class:`KernelUnavailable` as :func:`cpu_kernels`."""
    _require("backwards")
    return torch.ops.torch_ao_kernels


#: why a library could not be built, by library (the last try's message)
_FAILURES: dict[str, str] = {}


def _require(library: str) -> None:
    if not _loaded(library):
        raise KernelUnavailable(_FAILURES[library])


@torch.compiler.assume_constant_result
def _loaded(library: str) -> bool:
    """Build (once a process) and load the ``"forwards"`` or the ``"backwards"`` library: whether it is loaded
    (if not, :data:`_FAILURES` says why). ``torch.compile`` calls it while tracing and keeps its result as a
    constant, so a compiled call neither traces the build nor breaks its graph on it, and where the build fails it
    raises :class:`KernelUnavailable` in the traced code, which the dispatch catches as it does eagerly."""
    try:
        (_load_forwards if library == "forwards" else _load_backwards)()
    except KernelUnavailable as exc:
        _FAILURES[library] = str(exc)
        return False
    return True


@functools.lru_cache(maxsize=None)
def _load_forwards() -> None:
    load_cpu_library("torch_ao_kernels", _SOURCES)
    _register_fake()


@functools.lru_cache(maxsize=None)
def _load_backwards() -> None:
    _load_forwards()
    load_walk_grad_library()

    @torch.library.register_fake("torch_ao_kernels::walk_record")
    def _(accumulator, positions, normals, inverse_depth, depth, valid, intrinsics, cells, ints, floats, channels,
          words, scalar):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, channels, H, W), positions.new_empty((B, H, W, words), dtype=torch.int64)

    @torch.library.register_fake("torch_ao_kernels::walk_backward")
    def _(accumulator, grad, positions, normals, inverse_depth, depth, valid, intrinsics, cells, ints, floats, record,
          fetches, settings, camera, scalar):
        B, H, W, _ = positions.shape
        return (positions.new_empty(positions.shape), normals.new_empty(normals.shape),
                inverse_depth.new_empty(inverse_depth.shape), depth.new_empty(depth.shape),
                depth.new_empty((B, H, W, settings)), positions.new_empty((B, H, W, 4) if camera else (0,)))

    @torch.library.register_fake("torch_ao_kernels::soft_backward")
    def _(grad, positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface, ints, floats,
          camera, scalar):
        return (positions.new_empty(positions.shape), normals.new_empty(normals.shape),
                inverse_depth.new_empty(inverse_depth.shape), depth.new_empty(depth.shape),
                depth.new_empty((*depth.shape, 3)), depth.new_empty(depth.shape),  # (offset, scale, growth; the layer's)
                positions.new_empty(positions.shape),  # (the light's: zeros without indirect light)
                depth.new_empty((*depth.shape, 4) if camera else (0,)))

    @torch.library.register_fake("torch_ao_kernels::hard_record")
    def _(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface, ints, floats, channels,
          slices, scalar):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, channels, H, W), positions.new_empty((B, H, W, slices), dtype=torch.int32)

    @torch.library.register_fake("torch_ao_kernels::hard_backward")
    def _(grad, positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface, ints, floats,
          record, camera, scalar):
        return (positions.new_empty(positions.shape), normals.new_empty(normals.shape),
                inverse_depth.new_empty(inverse_depth.shape), depth.new_empty(depth.shape),
                positions.new_empty(positions.shape),  # (the light's: (B, H, W, 3), zeros without indirect light)
                depth.new_empty((*depth.shape, 4) if camera else (0,)))

    @torch.library.register_fake("torch_ao_kernels::exact_backward")
    def _(grad, positions, normals, inverse_depth, depth, valid, intrinsics, cells, backface, ints, floats, camera,
          scalar):
        return (positions.new_empty(positions.shape), normals.new_empty(normals.shape),
                inverse_depth.new_empty(inverse_depth.shape), depth.new_empty(depth.shape),
                depth.new_empty(depth.shape), depth.new_empty((*depth.shape, 4) if camera else (0,)))


def cpu_build_options() -> tuple[str, list[str], list[str]]:
    """``(name suffix, compiler flags, linker flags)`` of the C++ CPU libraries on this machine."""
    capability = torch.backends.cpu.get_cpu_capability()
    # -fopenmp: ATen's parallel_for is a header template, threaded only where the including code is
    # built with OpenMP (as Inductor builds its kernels); without it the walk runs on one thread
    flags = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fopenmp"] + _CAPABILITY_FLAGS.get(capability, [])
    vml = torch.backends.mkl.is_available()  # torch.cos/sin then use MKL's vector math: the kernel too
    if vml:
        flags.append("-DTORCH_AO_MKL_VML")
    return f"{capability.lower()}{'_vml' if vml else ''}", flags, ["-fopenmp"]


def load_walk_grad_library() -> Path:
    """Build (once) and load the backwards' library (walk_grad_cpu.cpp) without registering its fake kernels."""
    # (its dual lanes' zero tangents: GCC turns their zeroing loops into memset calls, which dead-store elimination
    # does not remove where the tangents are then written; as stores of lanes it does: 3-8 % of its backwards)
    return load_cpu_library("torch_ao_walk_grad", (Path(__file__).with_name("walk_grad_cpu.cpp"),),
                            ["-fno-tree-loop-distribute-patterns"])


def load_cpu_library(prefix: str, sources, extra_flags=()) -> Path:
    """Build (once) and load the CPU operator library ``<prefix>_<capability>_<place>`` from ``sources``, compiled
    with :func:`cpu_build_options`' flags and ``extra_flags``.

    ``place`` names where the sources are, so that checkouts sharing one ``$TORCH_EXTENSIONS_DIR``
    keep a build each instead of rebuilding it in turn (cpp_extension rebuilds when a source's path
    changes). Raises :class:`KernelUnavailable` when it cannot be built (the message says why)."""
    suffix, flags, ldflags = cpu_build_options()
    place = hashlib.sha256("\0".join(str(Path(s).resolve()) for s in sources).encode()).hexdigest()[:8]
    try:
        return load_cached_library(f"{prefix}_{suffix}_{place}", sources, [*flags, *extra_flags], ldflags)
    except Exception as exc:  # no compiler, missing headers, a failed build...
        raise KernelUnavailable(f"the C++ kernels could not be built ({type(exc).__name__}: "
                                f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else exc})") from exc


#: Written next to a built library: the fingerprint of what it was built from.
_STAMP = "torch_ao_build.sha256"
#: Locked (``flock``) by the process that builds in the folder; the OS releases it when that process dies.
_LOCK = "torch_ao_build.lock"
#: The file cpp_extension creates while it builds, and waits on (forever) while it exists.
_TORCH_LOCK = "lock"


def _fingerprint(sources, cflags, ldflags) -> str:
    """SHA-256 of everything a build depends on that can change between processes: the sources, the
    headers beside them and in this folder, the flags, torch (its headers) and the interpreter."""
    h = hashlib.sha256()
    for item in (torch.__version__, torch.__file__, sys.version, sys.executable, *cflags, "|", *ldflags):
        h.update(str(item).encode() + b"\0")
    files = {Path(s).resolve() for s in sources}
    for folder in {f.parent for f in files} | {_SOURCES[0].parent.resolve()}:  # (shared headers live here)
        files.update(p.resolve() for ext in ("*.h", "*.hpp", "*.cuh") for p in folder.glob(ext))
    for f in sorted(files):
        h.update(str(f).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def load_cached_library(name: str, sources, cflags, ldflags) -> Path:
    """Build (when needed) and load the operator library ``name`` from C++ ``sources``; returns its path.

    ``cpp_extension.load`` runs ninja in every new process (its record of what was built lives only in
    memory), about 5 s on a busy 2-core machine even when nothing changed. A stamp file beside the
    library holds the :func:`_fingerprint` of its inputs: when it matches, the library is loaded
    directly (milliseconds); otherwise ``cpp_extension.load`` builds it (ninja rebuilds what changed)
    and the stamp is rewritten.

    A build holds :func:`_build_lock` on the folder: a second process waits for it and then loads what
    it built, and cpp_extension's own ``lock`` file, which a build killed with SIGKILL leaves behind
    (and every later build would wait on forever), is removed as stale.
    """
    from torch.utils import cpp_extension

    folder = Path(cpp_extension._get_build_directory(name, verbose=False))
    fingerprint = _fingerprint(sources, cflags, ldflags)
    library = _current_library(folder, fingerprint)
    if library is None:
        with _build_lock(folder):
            library = _current_library(folder, fingerprint)  # (built by the process we waited for)
            if library is None:
                (folder / _TORCH_LOCK).unlink(missing_ok=True)  # under our lock, no live build owns it
                return _build(cpp_extension, name, folder, fingerprint, sources, cflags, ldflags)
    torch.ops.load_library(str(library))
    return library


def _current_library(folder: Path, fingerprint: str) -> Path | None:
    """The library the stamp in ``folder`` records for ``fingerprint``, if it is there."""
    stamp = folder / _STAMP
    recorded = stamp.read_text(encoding="utf-8").split() if stamp.exists() else []
    if len(recorded) == 2 and recorded[0] == fingerprint and (folder / recorded[1]).is_file():
        return folder / recorded[1]
    return None


@contextlib.contextmanager
def _build_lock(folder: Path):
    """Hold an exclusive ``flock`` on ``folder/torch_ao_build.lock`` (waiting, with a note on stderr, while
    another process holds it). The OS releases it when its holder exits or is killed, so it is never
    stale. Where ``fcntl`` is missing (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / _LOCK, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"torch_ao: waiting for another process building the C++ kernels in {folder}", file=sys.stderr)
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _build(cpp_extension, name: str, folder: Path, fingerprint: str, sources, cflags, ldflags) -> Path:
    """``cpp_extension.load`` (build and load) in ``folder``, then the stamp of ``fingerprint``."""
    stamp = folder / _STAMP
    stamp.unlink(missing_ok=True)  # a build interrupted from here on leaves no stale stamp
    # cpp_extension builds only when its in-process record of the sources changed: after a failed build, a second
    # try in the same process would load the library left from an older build, which the stamp would then call current
    cpp_extension.JIT_EXTENSION_VERSIONER.entries.pop(name, None)
    built = cpp_extension.load(name=name, sources=[str(s) for s in sources], extra_cflags=list(cflags),
                               extra_ldflags=list(ldflags), is_python_module=False, build_directory=str(folder),
                               verbose=bool(os.environ.get("TORCH_AO_KERNELS_VERBOSE")))
    # (torch 2.4 loads the library and returns None; later releases return its path, which is this one)
    library = Path(built) if built is not None else folder / f"{name}{cpp_extension.LIB_EXT}"
    tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}.tmp")
    tmp.write_text(f"{fingerprint} {library.name}\n", encoding="utf-8")
    os.replace(tmp, stamp)
    return library


def _register_fake() -> None:
    """Shapes of the kernels' outputs for tracing (``torch.compile`` calls the op as one graph node)."""

    @torch.library.register_fake("torch_ao_kernels::walk")
    def _(accumulator, positions, *args):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, args[-2], H, W)  # args[-2]: channels

    @torch.library.register_fake("torch_ao_kernels::scale_derivative")
    def _(valid, gradients, inputs):
        return valid.new_empty((), dtype=torch.float64)

"""Running the one walk (``walk.h``): its settings packed once, then the CPU operator or the CUDA kernel.

The walk's and an accumulator's settings travel as two small arrays (int64, float32) that ``packed.h``
reads, the same on every backend. On CPU the ``torch_ao_kernels::walk`` operator runs them (SIMD lanes, or
``lanes="scalar"``: each pixel through ``walk_pixel``, the CUDA thread's body). On CUDA the headers are
compiled at run time with NVRTC (``torch.cuda._compile_kernel``, which CUDA builds of torch ship: no CUDA
toolkit needed), one thread per pixel, in two builds: the lean one, and the full one (``TAO_FULL_WALK``, compiled
on first use) for the calls that need an option the lean one leaves out (:func:`full_walk`). Each build compiles a
group of entries at a time (:func:`cuda_groups`), the first time a call needs one of them.
"""
from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import re
from pathlib import Path

import torch

from ..gbuffer import GBuffer
from .build import KernelUnavailable, cpu_kernels
from ..checks import check_choice
from ..walk import NOISES as SLICE_NOISES, SLICE_SAMPLINGS
from ..walk.fetch import cell_flags
from .frame import scalar_lanes, walk_inputs

__all__ = ["PLACEMENTS", "NOISES", "walk_settings", "run_walk", "run_packed", "packed_inputs", "packed_settings",
           "full_walk", "cuda_source", "cuda_entry_names", "cuda_groups", "cuda_group_of", "cuda_options"]

#: step placements in packed.h's numbering (SlicePattern's, HDRP's and UE4's ShaderStepPattern, GLSLPattern's,
#: UE4 SSAO's WedgePattern, PSSAOPattern's integer pixel offsets, SSAO's hemisphere kernel points)
PLACEMENTS = ("power", "hdrp", "ue4", "glsl", "wedge", "pixels", "hemisphere")
#: the noise of the slice angles and steps in packed.h's numbering (walk.h's Noise): SlicePattern's
#: (:data:`torch_ao.walk.NOISES`: interleaved gradient noise, the Hilbert-indexed R2 sequence), then the GLSL
#: shader's one jitter in float32 or in float16 (``glsl_numerics="mesa_mediump"``)
NOISES = (*SLICE_NOISES, "glsl", "glsl_mediump")

_HERE = Path(__file__).parent
#: the CUDA source in dependency order: each header once, then the entry points
_CUDA_FILES = ("lanes_scalar.h", "slopes.h", "lanes_dual.h", "walk.h", "horizon.h", "bitmask.h", "bitmask_glsl.h", "soft.h", "soft_glsl.h", "ssao.h",
               "lanes_rev.h", "exact_soft.h", "packed.h", "walk_grad.h", "walk_cuda.cu")
_WALK_FLOATS = 4  # packed.h's kAccFloats: the walk's own floats
_THREADS = 128  # per block: a walk holds a few hundred registers' worth of state per pixel
# --fmad=false: a * b + c rounded twice, as the CPU kernels (-ffp-contract=off) and the tensor walk round it. With
# NVRTC's fused multiply-adds a sample's texel or the GLSL shader's hash (fract of a large product) can land on the
# other side of a boundary: on an H200, 2 of 4,348 pixels of a hard mask 28 sectors apart and 119 of the shader's,
# against none without; 9 % (hard bitmask AO) to 29 % (GTAO) of the walk's time at 1920x1080.
_NVRTC_OPTIONS = ("-std=c++17", "--fmad=false")
#: the full build's define (walk.h): the options whose registers the lean build saves every walk
_FULL_DEFINE = "-DTAO_FULL_WALK"
#: the accumulators that weigh their slices in the lean CUDA build too (horizon.h's): they take slices drawn by the
#: projected normal's density there
_WEIGH_SLICES_LEAN = ("gtao", "hbao")


def walk_settings(*, slices: int, steps: int, radius: float, jitter: bool, seed: int, fetch: str, border: str,
                  step_power: float = 1.0, min_step_px: float = 1.0, max_radius_px: float | None = None,
                  placement: str = "power", full_circle: bool = False, azimuth: str = "view",
                  sphere_extent: bool = False, noise: str = "ign", stagger: bool = False,
                  slice_sampling: str = "uniform", table: list[float] | None = None) -> tuple[list[int], list[float]]:
    """The walk's part of the packed settings ``(ints, floats)`` (packed.h's ``unpack_walk``).

    slices, steps: counts walked; radius: world units the walk covers; fetch ``"bilinear"``/``"nearest"``/
    ``"edge_aware"``, border ``"drop"``/``"clamp"``, step_power, min_step_px and max_radius_px (pixels;
    ``None``: none), placement (:data:`PLACEMENTS`), full_circle (HBAO's directions; one side per slice),
    azimuth ``"view"``/``"screen"``, sphere_extent (the steps over the radius' sphere's screen extent),
    noise (:data:`NOISES`: the jitter's kind), stagger (the step offsets shifted per half-slice), slice_sampling
    (``"uniform"``, or ``"projected_normal"``: the slices drawn by the projected normal's density, around the view
    vector over the half circle; the accumulators that weigh their slices take them, GTAO's and the bitmask
    family's: walk.h's walked_slice), table: the
    ``"wedge"`` placement's per slice (screen angle in radians, length) of a sample set (``None``: slices evenly
    over the half circle, length 1), the ``"pixels"`` placement's per slice and step ``(du, dv)`` in pixels, the
    ``"hemisphere"`` placement's per step its kernel point ``(x, y, z)`` (unit hemisphere, ``z`` along the normal;
    one slice over the full circle) (its floats follow the walk's four here; :func:`packed_settings` moves them
    after the accumulator's).
    """
    if placement == "pixels" and (table is None or len(table) != 2 * slices * steps):
        raise ValueError(f"table: the 'pixels' placement needs (du, dv) per slice and step ({2 * slices * steps} floats)")
    if placement == "wedge" and table is not None and len(table) != 2 * slices:
        raise ValueError(f"table: the 'wedge' placement takes (angle, length) per slice ({2 * slices} floats)")
    if placement == "hemisphere" and (table is None or len(table) != 3 * steps or slices != 1 or not full_circle):
        raise ValueError(f"table: the 'hemisphere' placement needs (x, y, z) per step ({3 * steps} floats) over one "
                         "slice on the full circle")
    check_choice("slice_sampling", slice_sampling, SLICE_SAMPLINGS)
    if slice_sampling == "projected_normal" and (azimuth != "view" or full_circle or
                                                 placement not in ("power", "hdrp", "ue4")):
        raise ValueError("slice_sampling: 'projected_normal' draws slice azimuths around the view vector over a half "
                         f"circle (got azimuth={azimuth!r}, full_circle={full_circle}, placement={placement!r})")
    if table is not None and placement not in ("wedge", "pixels", "hemisphere"):
        raise ValueError(f"table: only the 'wedge', 'pixels' and 'hemisphere' placements read one, not {placement!r}")
    ints = [int(slices), int(steps), int(seed), PLACEMENTS.index(placement), bool(jitter), fetch != "nearest",
            border == "drop", bool(full_circle), azimuth == "screen", fetch == "edge_aware", bool(sphere_extent),
            NOISES.index(noise), bool(stagger), 0, False,  # (the table's start and unprojected: packed_inputs')
            slice_sampling == "projected_normal"]
    floats = [radius if isinstance(radius, torch.Tensor) else float(radius), float(step_power), float(min_step_px),
              float(max_radius_px or 0.0)]
    floats += [float(v) for v in table or ()]
    return [int(v) for v in ints], floats


def full_walk(accumulator: str, gbuffer: GBuffer, settings: tuple[list[int], list[float]], *,
              segments: bool = False) -> bool:
    """Whether a CUDA walk with ``accumulator`` over ``gbuffer`` with the walk ``settings`` (:func:`walk_settings`')
    needs the full build (walk.h's ``TAO_FULL_WALK``): a position buffer read between texels, slices drawn by the
    projected normal's density in an accumulator other than the horizon ones (:data:`_WEIGH_SLICES_LEAN`), or
    ``segments``: the soft accumulators' segment geometry (the ``"exact"`` variant's). The CPU's has everything."""
    walk = settings[0]
    reads_positions = bool(walk[5]) and gbuffer.position is not None  # (bilinear: fetch != "nearest")
    return reads_positions or (bool(walk[15]) and accumulator not in _WEIGH_SLICES_LEAN) or bool(segments)


def run_walk(accumulator: str, gbuffer: GBuffer, normals: torch.Tensor, settings: tuple[list[int], list[float]],
             acc_ints: list, acc_floats: list, channels: int, *, light: torch.Tensor | None = None,
             backface: torch.Tensor | None = None, lanes: str = "simd", segments: bool = False) -> torch.Tensor:
    """The walk with ``accumulator`` (``"gtao"``, ``"hbao"``, ``"bitmask"``, ``"exact"``, ``"glsl"``, ``"wedge"``,
    ``"pssao"``, ``"hemisphere"``, ``"soft"``) over ``gbuffer`` (float32, CPU or CUDA): its ``channels`` per pixel, ``(B, channels, H, W)``.

    ``settings`` is :func:`walk_settings`'s; ``acc_ints``/``acc_floats`` the accumulator's (packed.h);
    ``light``: the channel-last ``(B,H,W,3)`` light or ``None``; ``backface``: the back-face thickness
    layer ``(B,1,H,W)`` or ``None``; ``lanes``: on CPU, ``"simd"`` or ``"scalar"``; ``segments``: the soft
    accumulators' segment geometry is on (:func:`full_walk`).
    Raises :class:`KernelUnavailable` when the backend's kernel cannot be built here.
    """
    full = full_walk(accumulator, gbuffer, settings, segments=segments)
    with torch.no_grad():  # no kernel of the walk has a backward: the dispatch sends gradients to the tensor path
        inputs, extra, ints, floats = packed_inputs(gbuffer, normals, settings, acc_ints, acc_floats, light, backface)
        return run_packed(accumulator, inputs, extra, ints, floats, channels, scalar_lanes(lanes), full=full)


def run_packed(accumulator: str, inputs, extra, ints: torch.Tensor, floats: torch.Tensor, channels: int,
               scalar: bool, *, full: bool = False) -> torch.Tensor:
    """The walk with ``accumulator`` over :func:`packed_inputs`' ``inputs`` (six tensors), ``extra`` (light,
    cells, back-face layer) and packed settings: the CPU operator (``scalar``: its scalar lanes) or the CUDA
    kernel (``full``: of the full build, :func:`full_walk`), ``(B, channels, H, W)``."""
    device = inputs[3].device
    if device.type == "cpu":
        return cpu_kernels().walk(accumulator, *inputs, *extra, ints, floats, int(channels), scalar)
    if device.type != "cuda":
        raise KernelUnavailable(f"no kernel for a G-buffer on {device.type}")
    B, H, W = inputs[3].shape
    out = torch.empty(B, channels, H, W, device=device)
    launch_cuda(f"tao_walk_{accumulator}", device, [*inputs, *extra, out, ints, floats], (B, H, W), full=full)
    return out


def launch_cuda(name: str, device: torch.device, args: list, shape: tuple[int, int, int], *,
                full: bool = False) -> None:
    """The CUDA kernel ``name`` of walk_cuda.cu (compiled on first use; ``full``: the full build's,
    :func:`full_walk`) over the ``(B, H, W)`` pixels of ``shape``, one thread each, with ``args`` (tensors as
    pointers, then the shape's three ints)."""
    kernel = _cuda_kernel(name, device.index if device.index is not None else torch.cuda.current_device(), full)
    B, H, W = shape
    kernel(grid=(-(-B * H * W // _THREADS), 1, 1), block=(_THREADS, 1, 1), args=[*args, B, H, W])


def packed_inputs(gbuffer: GBuffer, normals: torch.Tensor, settings: tuple[list[int], list[float]], acc_ints: list,
                  acc_floats: list, light: torch.Tensor | None = None, backface: torch.Tensor | None = None) -> tuple:
    """What every backend's walk reads, on the G-buffer's device: :func:`walk_inputs`' six tensors, the
    optional images ``(light, cells, backface)`` (each empty where unused: the cells are the edge-aware
    fetch's :func:`~torch_ao.walk.fetch.cell_flags`), and the packed ``ints`` (int64) and ``floats``
    (float32)."""
    device = gbuffer.depth.device
    inputs = walk_inputs(gbuffer, normals)
    ints = list(settings[0])
    ints[14] = gbuffer.position is None  # (unprojected: no position buffer)
    settings = (ints, settings[1])

    def none():  # (one tensor each: torch.compile does not trace an autograd Function given one tensor twice)
        return torch.empty(0, device=device)

    cells = none()
    if settings[0][9]:  # edge_aware (the flags have no gradient: kept with the G-buffer between calls)
        inverse, valid = inputs[2], inputs[4]
        cells = gbuffer.derived("edge_aware_cells", lambda: cell_flags(torch.where(valid, inverse.detach(), 0.0))
                                .to(torch.float32).contiguous())
    layer = none() if backface is None else backface[:, 0].to(torch.float32).contiguous()
    return inputs, (none() if light is None else light, cells, layer), *packed_settings(settings, acc_ints, acc_floats,
                                                                                      device)


def packed_settings(settings: tuple[list[int], list[float]], acc_ints: list, acc_floats: list,
                    device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The walk's and the accumulator's settings as packed.h reads them: ``ints`` (int64), ``floats`` (float32):
    the walk's, the accumulator's, then the walk's table (its start in ``ints[13]``). A float may be a 0-d tensor
    (a parameter). Nothing is read back from a GPU nor copied to it, so a CUDA call never waits for the GPU: the
    numbers are kept on the device per value (the kernels only read them), and the tensors join them there."""
    walk_ints, walk_floats, table = list(settings[0]), settings[1][:_WALK_FLOATS], settings[1][_WALK_FLOATS:]
    walk_ints[13] = _WALK_FLOATS + len(acc_floats) if table else 0
    ints, values = tuple(walk_ints + [int(v) for v in acc_ints]), [*walk_floats, *acc_floats, *table]
    device = torch.device(device)
    given = tuple(k for k, v in enumerate(values) if isinstance(v, torch.Tensor))
    ints, floats = _settings_tensors(ints, tuple(0.0 if k in given else float(v) for k, v in enumerate(values)), device)
    if not given:
        return ints, floats
    at = _settings_tensors(given, (), device)[0]
    tensors = torch.stack([values[k].detach().reshape(()).to(device, torch.float32) for k in given])
    return ints, floats.index_put((at,), tensors)


def _settings_tensors(ints: tuple, floats: tuple, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    if torch.compiler.is_compiling():  # (constants of the graph: torch.compile does not trace a cache)
        return _new_settings_tensors(ints, floats, device)
    return _cached_settings_tensors(ints, floats, device)


def _new_settings_tensors(ints: tuple, floats: tuple, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor(ints, dtype=torch.int64, device=device),
            torch.tensor(floats, dtype=torch.float32, device=device))


_cached_settings_tensors = functools.lru_cache(maxsize=256)(_new_settings_tensors)


@contextlib.contextmanager
def thread_locale_kept():
    """Restore the calling thread's C locale on exit. NVRTC 12.1 (CUDA 12.1 builds of torch) leaves the thread that
    compiled in a "C" locale of its own (``uselocale``), after which Python opens text files in ASCII in that thread:
    the user's program too, not only this library. Where the C library has no ``uselocale``, nothing is done."""
    try:
        uselocale = ctypes.CDLL(None).uselocale
    except (AttributeError, OSError):  # pragma: no cover - Windows
        yield
        return
    uselocale.restype, uselocale.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
    kept = uselocale(None)  # (None asks without changing it)
    try:
        yield
    finally:
        uselocale(kept)


def cuda_source() -> str:
    """The CUDA kernels' source as NVRTC compiles it: the headers inlined in order, then ``walk_cuda.cu``."""
    parts = []
    for name in _CUDA_FILES:
        text = (_HERE / name).read_text(encoding="utf-8")
        text = re.sub(r'^\s*#\s*(pragma once|include\s+"[^"]+")\s*$', "", text, flags=re.M)
        parts.append(f"// ---- {name}\n{text}")
    return "\n".join(parts)


def cuda_entry_names(source: str | None = None) -> tuple[str, ...]:
    """The ``__global__`` entry points of ``source`` (default :func:`cuda_source`): one name per
    ``TAO_CUDA_ENTRY`` / ``RECORD`` / ``BACKWARD`` / ``SOFT_BACKWARD`` macro or plain ``__global__`` function, two per
    ``TAO_CUDA_HARD`` (its record and backward)."""
    source = cuda_source() if source is None else source
    names = re.findall(r"^(?:TAO_CUDA_(?:ENTRY|RECORD|BACKWARD|SOFT_BACKWARD)\(|extern \"C\" __global__ void )(\w+)", source,
                       flags=re.M)
    for pair in re.findall(r"^TAO_CUDA_HARD\((\w+), (\w+),", source, flags=re.M):
        names += pair
    return tuple(names)


def cuda_groups(source: str | None = None) -> dict[str, tuple[str, ...]]:
    """walk_cuda.cu's groups of entry points, ``{group: names}`` in the source's order: each group is the entries
    between ``#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_<GROUP>)`` and the next ``#endif`` of ``source``
    (default :func:`cuda_source`), which a build given ``TAO_ONE_GROUP`` and that ``TAO_GROUP_<GROUP>`` compiles
    alone (:func:`cuda_options`)."""
    source = cuda_source() if source is None else source
    groups = {}
    for group, body in re.findall(r"^#if !defined\(TAO_ONE_GROUP\) \|\| defined\(TAO_GROUP_(\w+)\)\n(.*?)^#endif",
                                  source, flags=re.M | re.S):
        groups[group.lower()] = cuda_entry_names(body)
    return groups


def cuda_options(full: bool = False, group: str | None = None) -> list[str]:
    """NVRTC's options for the lean build, or the ``full`` one (walk.h's ``TAO_FULL_WALK``), of every entry point or
    of one of :func:`cuda_groups`."""
    one_group = ("-DTAO_ONE_GROUP", f"-DTAO_GROUP_{group.upper()}") if group else ()
    return [*_NVRTC_OPTIONS, *((_FULL_DEFINE,) if full else ()), *one_group]


@functools.lru_cache(maxsize=None)
def cuda_group_of() -> dict[str, str]:
    """Each entry point of walk_cuda.cu, and its group (:func:`cuda_groups`)."""
    return {name: group for group, names in cuda_groups().items() for name in names}


def _cuda_kernel(name: str, device_index: int, full: bool = False):
    """The compiled CUDA kernel ``name`` of walk_cuda.cu for the device, of the lean or the ``full`` build."""
    if name not in cuda_group_of():
        raise KernelUnavailable(f"walk_cuda.cu has no kernel {name}")
    kernels = _cuda_kernels(device_index, bool(full), cuda_group_of()[name])
    if isinstance(kernels, KernelUnavailable):
        raise kernels
    return kernels[name]


@functools.lru_cache(maxsize=None)
def _cuda_kernels(device_index: int, full: bool, group: str) -> dict | KernelUnavailable:
    """The kernels of one of walk_cuda.cu's groups (:func:`cuda_groups`) for the device, ``{name: kernel}``, of the
    lean or the ``full`` build: one NVRTC compile of the group (the walks take seconds, a horizon accumulator's
    backwards most of a minute), kept on disk by :func:`_cuda_binary`, so that a later process loads it in
    milliseconds. A failure is returned (and so kept) rather than raised: the process does not compile again at
    every call."""
    try:
        from torch.cuda._utils import _cuda_load_module, _nvrtc_compile

        with torch.cuda.device(device_index):
            major, minor = torch.cuda.get_device_capability(device_index)
            source, names, options = cuda_source(), cuda_groups()[group], cuda_options(full, group)

            def compile_source() -> bytes:  # (torch < 2.9 returns the binary alone, later ones with a name)
                with thread_locale_kept():
                    out = _nvrtc_compile(source, names[0], compute_capability=f"{major}{minor}",
                                         nvcc_options=options)
                return out[0] if isinstance(out, tuple) else out

            binary = _cuda_binary(source, options, f"{major}{minor}", compile_source)
            return _cuda_load_module(binary, list(names))
    except Exception as exc:  # no NVRTC in this build, a compile error...
        error = KernelUnavailable(f"the CUDA kernels could not be compiled ({type(exc).__name__}: "
                                  f"{str(exc).strip()[-2000:] if str(exc).strip() else exc})")
        error.__cause__ = exc
        return error


def cuda_cache_dir() -> Path:
    """Where compiled CUDA kernels are kept: ``$TORCH_AO_CUDA_CACHE``, else ``torch_ao_cuda`` beside the C++
    builds in ``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``)."""
    if os.environ.get("TORCH_AO_CUDA_CACHE"):
        return Path(os.environ["TORCH_AO_CUDA_CACHE"])
    from torch.utils.cpp_extension import get_default_build_root

    return Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()) / "torch_ao_cuda"


def _cuda_binary(source: str, options: list[str], arch: str, compile_source) -> bytes:
    """The binary ``compile_source()`` makes of ``source`` with NVRTC's ``options`` for compute capability ``arch``,
    from the disk cache when it holds one for the same source, options, architecture and CUDA/torch versions.
    Written to a temporary name and renamed into place, so that a process killed while writing leaves nothing that
    a later one would read."""
    key = hashlib.sha256("\0".join((source, *options, arch, str(torch.version.cuda), torch.__version__))
                         .encode()).hexdigest()[:24]
    path = cuda_cache_dir() / f"walk_sm{arch}_{key}.bin"
    if path.is_file():
        return path.read_bytes()
    binary = compile_source()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(binary)
        os.replace(tmp, path)
    except OSError:  # a read-only home: compiled again by the next process
        pass
    return binary

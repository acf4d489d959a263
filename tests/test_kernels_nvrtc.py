"""The CUDA kernels compiled by NVIDIA's own compilers on a machine without a GPU (torch_ao.kernels.cuda_offline):
NVRTC, as the kernels are compiled on a GPU, must accept the source for an H200 (compute capability 9.0) and
an A100 (8.0) and give every entry point of walk_cuda.cu; ptxas must assemble it, the walks without spilling
registers (the exact and hard backwards' dual lanes spill a little).
tests/test_kernels_cuda.py runs the same source's logic on the CPU; on a GPU, the kernels run for real."""
import re

import pytest

from torch_ao.kernels import cuda_offline

pytestmark = [pytest.mark.skipif(cuda_offline.nvrtc_library() is None,
                                 reason="needs NVRTC (pip install nvidia-cuda-nvrtc-cu12)"),
              pytest.mark.xdist_group("nvrtc")]  # (one worker: the module's compile of every group is shared)


@pytest.fixture(scope="module")
def ptx90():
    """Each group's PTX for an H200, compiled alone as a GPU compiles it: ``{group: ptx}``."""
    return cuda_offline.compile_groups(90)


def test_entry_points_are_found():
    names = cuda_offline.KERNEL_NAMES
    assert len(names) >= 14 and {"tao_walk_gtao", "tao_record_hbao", "tao_backward_gtao"} <= set(names)


@pytest.mark.parametrize("arch", [pytest.param(80, marks=pytest.mark.slow), 90])
def test_nvrtc_compiles_every_group_with_its_entries_and_no_other(request, arch):
    """Every entry point is in one group of walk_cuda.cu (launch.cuda_groups), and a build of one group (TAO_ONE_GROUP:
    what a call compiles at its group's first use) holds that group's entries and no other."""
    from torch_ao.kernels.launch import cuda_groups

    groups = cuda_groups()
    names = [name for group in groups.values() for name in group]
    assert sorted(names) == sorted(cuda_offline.KERNEL_NAMES) and len(set(names)) == len(names)
    assert {"walks", "records", "gtao_small", "gtao_short", "gtao", "hbao_small", "hbao_short", "hbao", "ssao",
            "soft", "exact", "hard"} == set(groups)
    ptx = request.getfixturevalue("ptx90") if arch == 90 else cuda_offline.compile_groups(arch)
    assert set(ptx) == set(groups)
    for group, module in ptx.items():
        assert f".target sm_{arch}" in module, group
        assert sorted(re.findall(r"\.entry (\w+)\(", module)) == sorted(groups[group]), group


def test_a_compile_error_is_reported_with_the_log(monkeypatch):
    monkeypatch.setattr(cuda_offline, "cuda_source", lambda: "__global__ void broken( { }")
    with pytest.raises(RuntimeError, match="(?s)NVRTC could not compile.*walk_cuda.cu.1.: error"):
        cuda_offline.compile_ptx(90)


@pytest.mark.skipif(cuda_offline.ptxas_path() is None, reason="needs ptxas (pip install nvidia-cuda-nvcc-cu12)")
def test_ptxas_assembles_every_kernel_and_the_walks_without_spilling(ptx90):
    """A walk keeps its pixel's state in registers: none spills but the hard sector walk, held to 170 registers (3 blocks
    of 128 threads a multiprocessor, walk_cuda.cu's launch bounds: 60 bytes; the exact union's walk is held to 128, 4
    blocks, and spills nothing), nor does the horizon backward, whose replay
    keeps its tape in the thread's local memory (lanes_rev.h), sized by the fetches a slice replays: 17-18 kB in the
    _small entries (4), 35-36 kB in the _short ones (16), 106-107 kB in the full ones (64; the driver reserves a
    thread's stack for every thread of the GPU, so the small entries' bounds are asserted). The exact
    union's backward replays an interval's segment in 11 tangents: 1464 bytes spilled and reloaded; the hard
    sector walk's ends each slice with its 32 sectors' weights in 2 tangents and replays the steps that send
    indirect light in 16: 4352 bytes; the short soft backward, whose slice's steps fit in 11 kB of local memory
    (against 87 kB), 1932 bytes, and the long one 472 (its indirect light's replay in 9 tangents and the bent normal's
    terms take it past 255 registers; it keeps 87 kB of local memory a thread whatever it spills); bounded here
    (NVRTC 12.9, sm_90). The ssilvb_glsl shader's light backward (closed forms) and its soft backward spill nothing.
    Older NVRTC releases allocate otherwise (12.1, torch 2.4's: the exact union's walk spills 8 bytes)."""
    if cuda_offline.nvrtc_version() < (12, 9):
        pytest.skip(f"the spills are bounded for NVRTC 12.9 and later, not {cuda_offline.nvrtc_version()}")
    report = cuda_offline.kernel_resources(ptx90, 90)
    assert set(report) == set(cuda_offline.KERNEL_NAMES)
    bounds = {"tao_exact_backward": 2048, "tao_hard_backward": 5120, "tao_walk_bitmask": 96,  # bytes spilled, reloaded
              "tao_soft_backward_short": 2048, "tao_soft_backward": 640}
    stacks = {"_small": 20 * 1024, "_short": 40 * 1024}  # the horizon backwards' (bytes)
    for name, used in report.items():
        assert 32 <= used.registers <= 255, (name, used)
        spilled = used.spill_stores + used.spill_loads
        assert spilled <= bounds.get(name, 0), (name, used)
        assert 0 < used.occupancy(128) <= 1
        for suffix, most in stacks.items():
            if name.startswith("tao_backward_") and name.endswith(suffix):
                assert used.stack <= most, (name, used)
    assert sum(name.startswith("tao_backward_") and name.endswith("_small") for name in report) == 3


def test_occupancy_follows_the_registers():
    """Closed forms on compute capability 9.0: 65536 registers per SM, allocated per warp in units of 256,
    at most 64 warps and 32 blocks."""
    def at(registers, threads=128):
        return cuda_offline.KernelResources(registers, 0, 0, 0).occupancy(threads)
    assert at(32) == 1.0  # 64 warps of 32 x 32 registers fill the SM exactly
    assert at(128) == 0.25  # 16 warps: 4 blocks of 4
    assert at(168) == 12 / 64  # 5376 registers a warp: 12 warps, 3 blocks
    assert at(247) == 8 / 64  # 7936 (248 x 32) a warp: 8 warps, 2 blocks
    assert at(32, threads=32) == 0.5  # 32 blocks of one warp at most


def test_the_compiled_kernels_are_kept_on_disk_once(tmp_path, monkeypatch):
    """The CUDA binary is compiled once per source, architecture and CUDA version, then read from
    ``$TORCH_AO_CUDA_CACHE``; a write is renamed into place, so nothing half-written is ever read."""
    from torch_ao.kernels import launch

    monkeypatch.setenv("TORCH_AO_CUDA_CACHE", str(tmp_path))
    calls = []

    def compile_source(blob=b"\x7fELF cubin"):
        calls.append(1)
        return blob

    lean, full = launch.cuda_options(), launch.cuda_options(full=True)
    assert launch._cuda_binary("source a", lean, "90", compile_source) == b"\x7fELF cubin"
    assert launch._cuda_binary("source a", lean, "90", lambda: pytest.fail("compiled twice")) == b"\x7fELF cubin"
    assert launch._cuda_binary("source b", lean, "90", lambda: compile_source(b"other")) == b"other"
    assert launch._cuda_binary("source a", lean, "80", lambda: compile_source(b"sm80")) == b"sm80"
    # (the full build: a binary of its own)
    assert launch._cuda_binary("source a", full, "90", lambda: compile_source(b"full")) == b"full"
    assert len(calls) == 4
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".bin"] * 4  # (no temporary left behind)


def test_the_cuda_entry_names_follow_the_macros():
    from torch_ao.kernels.launch import cuda_entry_names

    source = ('TAO_CUDA_ENTRY(tao_walk_x, X)\nTAO_CUDA_HARD(tao_record_y, tao_backward_y, Y)\n'
              'extern "C" __global__ void tao_plain(int n) {}\n  TAO_CUDA_ENTRY(indented_is_a_use, Z)\n')
    assert cuda_entry_names(source) == ("tao_walk_x", "tao_plain", "tao_record_y", "tao_backward_y")


@pytest.mark.slow
@pytest.mark.skipif(cuda_offline.ptxas_path() is None, reason="needs ptxas (pip install nvidia-cuda-nvcc-cu12)")
def test_the_full_build_compiles_and_spills_little():
    """The full build (walk.h's TAO_FULL_WALK: slices drawn by the projected normal's density in the sector
    accumulators, a position buffer read between texels, the soft segment geometry), which only the calls that need
    one of them run: every entry point, within 255 registers; what the options add spills a little in the walks (the
    hard sector walk 164 bytes, its recording forward 32, the exact union's 140, the soft one's 32) and more in the
    backwards (the hard one 5892, the exact union's 2672, the soft ones' 2896-3168); bounded here (NVRTC 12.9, sm_90)."""
    report = cuda_offline.kernel_resources(cuda_offline.compile_groups(90, full=True), 90)
    assert set(report) == set(cuda_offline.KERNEL_NAMES)
    bounds = {"tao_exact_backward": 4096, "tao_hard_backward": 7168, "tao_walk_bitmask": 192, "tao_record_hard": 64,
              "tao_walk_exact": 192, "tao_walk_soft": 96, "tao_soft_backward_short": 4096, "tao_soft_backward": 4096}
    for name, used in report.items():
        assert 32 <= used.registers <= 255, (name, used)
        assert used.spill_stores + used.spill_loads <= bounds.get(name, 0), (name, used)

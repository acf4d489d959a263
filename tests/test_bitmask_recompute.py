"""Chunked, recomputed soft walks (the memory bound) give the values and gradients of a whole-frame
walk: the checkpoint's discarded first pass saves placeholders, the recomputation the real tables."""
import pytest
import torch

from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.methods.bitmask import SSILVB, BitmaskAO


@pytest.mark.parametrize("cls, mode", [(BitmaskAO, "soft"), (SSILVB, "soft"), (BitmaskAO, "straight_through")])
def test_recomputed_chunks_match_the_whole_frame(cls, mode):
    gb, _ = floor_wall_gbuffer(24, 32, dtype=torch.float64, light_direction=(0.3, 0.8, 0.5))
    results = []
    for options in (dict(chunk_size=None, recompute=False), dict(chunk_size=150, recompute=True)):
        depth = gb.depth.clone().requires_grad_(True)
        light = gb.light.clone().requires_grad_(True)
        module = cls(mode=mode, slices=2, steps=3, weighting="cosine", thickness=0.4, fetch="bilinear", **options).double()
        out = module(GBuffer(depth, gb.camera, normals=gb.normals, light=light))
        loss = out.visibility.sum() + (out.indirect.sum() if out.indirect is not None else 0)
        loss.backward()
        results.append([out.visibility.detach(), depth.grad, module.thickness.grad, module.radius.grad]
                       + ([light.grad] if out.indirect is not None else []))
    whole, chunked = results
    assert whole[1].abs().sum() > 0 and whole[2].abs() > 0
    for a, b in zip(whole, chunked):
        assert torch.allclose(a, b, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("variant", ["default", "exact"])
def test_recomputed_chunks_with_the_edge_aware_fetch(variant):
    """The edge-aware fetch's cell flags are computed once per frame, inside the first chunk: its recomputation
    finds them cached and must save what the first pass saved (a graph for the flags did not: the backward
    raised CheckpointError)."""
    gb, _ = floor_wall_gbuffer(24, 32, dtype=torch.float64)
    results = []
    for options in (dict(chunk_size=None, recompute=False), dict(chunk_size=150, recompute=True)):
        depth = gb.depth.clone().requires_grad_(True)
        module = BitmaskAO(variant=variant, mode="soft", slices=2, steps=3, fetch="edge_aware", backend="torch",
                           **options).double()
        out = module(GBuffer(depth, gb.camera, normals=gb.normals))
        out.visibility.sum().backward()
        results.append([out.visibility.detach(), depth.grad])
    (whole, g_whole), (chunked, g_chunked) = results
    assert g_whole.abs().sum() > 0
    assert torch.allclose(whole, chunked, atol=1e-12) and torch.allclose(g_whole, g_chunked, atol=1e-12, rtol=1e-10)


def test_auto_chunking_follows_the_mode_at_call_time():
    module = BitmaskAO(mode="hard", slices=4, steps=8)
    vga, hd, small = 640 * 360, 1280 * 720, BitmaskAO.default_chunk
    assert module.auto_chunking(vga) == (BitmaskAO.default_chunk, False)
    module.mode = "soft"  # as fit's set_mode does after construction
    # 640x360 at 4 x 8: the whole graph (about 0.7 GB) fits the budget, the walk runs once
    assert module.graph_bytes(vga) <= BitmaskAO.graph_budget
    assert module.auto_chunking(vga) == (BitmaskAO.default_chunk, False)
    # 1280x720 does not: recomputed chunks bound the memory
    assert module.auto_chunking(hd) == (BitmaskAO.default_soft_chunk, True)
    assert module.auto_chunking(small) == (None, False)
    with torch.no_grad():
        assert module.auto_chunking(hd) == (BitmaskAO.default_chunk, False)
    # indirect light keeps more per step: recomputed, half the chunk
    assert SSILVB(mode="soft", slices=4, steps=8).auto_chunking(vga) == (BitmaskAO.default_soft_chunk // 2, True)
    # the user's own settings are kept
    explicit = BitmaskAO(mode="soft", chunk_size=100, recompute=False)
    gb, _ = floor_wall_gbuffer(8, 8)
    explicit(gb)
    assert (explicit.chunk_size, explicit.recompute, explicit._auto_chunk) == (100, False, False)


@pytest.mark.parametrize("indirect", [False, True])
def test_hard_chunks_match_the_whole_frame(indirect, monkeypatch):
    gb, _ = floor_wall_gbuffer(24, 32, light_direction=(0.3, 0.8, 0.5))
    whole = BitmaskAO(mode="hard", indirect=indirect, chunk_size=None)(gb)
    monkeypatch.setattr(BitmaskAO, "default_chunk", 100)  # the automatic chunking, in 8 chunks
    chunked = BitmaskAO(mode="hard", indirect=indirect)(gb)
    assert torch.equal(whole.visibility, chunked.visibility)
    assert whole.visibility.min() < 0.9
    if indirect:
        assert torch.allclose(whole.indirect, chunked.indirect, atol=1e-7) and whole.indirect.max() > 0


def _saved_bytes_per_sample(module, gb) -> float:
    """Bytes of the distinct storages autograd saves for a forward, per pixel x slice x side x step."""
    saved = {}

    def pack(t):
        saved[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        module(gb)
    pixels = gb.depth.numel()
    return sum(saved.values()) / (pixels * module.slices * 2 * module.steps)


@pytest.mark.parametrize("indirect", [False, True])
def test_graph_estimate_bounds_what_autograd_keeps(indirect):
    gb, _ = floor_wall_gbuffer(48, 64, light_direction=(0.3, 0.8, 0.5))
    depth = gb.depth.clone().requires_grad_(True)
    gb = GBuffer(depth, gb.camera, normals=gb.normals.clone().requires_grad_(True), light=gb.light.clone().requires_grad_(True))
    # every step live (thick occluders, no narrowing): the most indirect light keeps
    dense = dict(thickness=1000.0, sector_epsilon=0.0) if indirect else {}
    module = BitmaskAO(mode="soft", slices=4, steps=8, indirect=indirect, chunk_size=None, recompute=False, backend="torch",
                       **dense)  # (the tensor path: the kernel keeps no graph)
    per_sample = _saved_bytes_per_sample(module, gb)
    estimate = module.graph_bytes_per_sample_indirect if indirect else module.graph_bytes_per_sample
    assert 0.5 * estimate < per_sample <= estimate


@pytest.mark.parametrize("weighting", ["uniform", "cosine"])
def test_indirect_light_gathered_for_live_steps_only_changes_nothing(weighting, monkeypatch):
    import torch_ao.methods.bitmask_common as bitmask

    gb, _ = floor_wall_gbuffer(24, 32, dtype=torch.float64, light_direction=(0.3, 0.8, 0.5))
    results, gathered = [], []
    original = bitmask._light_rows

    def spy(width):
        rows = original(width)
        gathered.append((len(rows), width.shape[0]))
        return rows

    monkeypatch.setattr(bitmask, "_light_rows", spy)
    for every_row in (False, True):
        if every_row:  # gather light for every step, empty intervals included
            monkeypatch.setattr(bitmask, "_light_rows", lambda width: torch.arange(width.shape[0]))
        depth, light = gb.depth.clone().requires_grad_(True), gb.light.clone().requires_grad_(True)
        normals = gb.normals.clone().requires_grad_(True)
        module = SSILVB(mode="soft", slices=2, steps=4, weighting=weighting, thickness=0.4).double()
        out = module(GBuffer(depth, gb.camera, normals=normals, light=light))
        loss = (out.indirect * torch.linspace(0, 1, out.indirect.numel(), dtype=torch.float64).view_as(out.indirect)).sum()
        results.append([out.indirect.detach()] + list(torch.autograd.grad(loss, (depth, normals, light, module.thickness))))
    live_only, every = results
    assert every[0].abs().max() > 0
    assert 0 < sum(m for m, _ in gathered) < 0.5 * sum(n for _, n in gathered)  # most steps occlude nothing
    for a, b in zip(live_only, every):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)


def test_graph_estimate_bounds_what_the_exact_variant_keeps():
    gb, _ = floor_wall_gbuffer(48, 64)
    depth = gb.depth.clone().requires_grad_(True)
    gb = GBuffer(depth, gb.camera, normals=gb.normals.clone().requires_grad_(True))
    module = BitmaskAO(variant="exact", slices=4, steps=8, chunk_size=None, recompute=False, backend="torch")
    per_sample = _saved_bytes_per_sample(module, gb)
    assert 0.5 * module.graph_bytes_per_sample_exact < per_sample <= module.graph_bytes_per_sample_exact
    # recorded in hard mode too (the exact union has gradients in every mode): chunks are recomputed when large
    assert module.auto_chunking(4 * module.graph_budget // (module.slices * 2 * module.steps * 400)) == (
        module.default_soft_chunk, True)

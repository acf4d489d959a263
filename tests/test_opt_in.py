"""Leave out what a scene does not need, checked by instrumentation (never by timing):

* outputs are opt-in: indirect light (the light buffer is neither handed to the core nor gathered),
  bent normals, and normals from depth (only when the G-buffer has none);
* background costs nothing: an all-background frame walks no pixel and returns ones, a half-background
  frame walks exactly half of them.
"""
import math

import pytest
import torch

import torch_ao.gbuffer as gbuffer_module
import torch_ao.methods.ssao as ssao_module
import torch_ao.walk as walk_package
import torch_ao.walk.walk as walk_module
from test_bench_helpers import TinyAO, importable_methods
from torch_ao import GBuffer
from torch_ao.bench import background_frames, background_scaling
from torch_ao.examples import example_gbuffer

H, W = 16, 24


@pytest.fixture
def probe(monkeypatch):
    """Records the buffers each Frame is given, the buffers samples gather, normals reconstructions,
    and the number of query pixels each walk covers."""
    log = {"buffers": [], "gathered": [], "normals_from_depth": 0, "walked": []}
    frame_init, gather, nfd = walk_package.Frame.__init__, walk_package.Sample.gather, gbuffer_module.normals_from_depth
    chunks = walk_module.march_chunks

    def frame_init_probe(self, gb, normals=None, buffers=None):
        log["buffers"].append(set(buffers or {}))
        frame_init(self, gb, normals=normals, buffers=buffers)

    def gather_probe(self, name):
        log["gathered"].append(name)
        return gather(self, name)

    def nfd_probe(*args, **kwargs):
        log["normals_from_depth"] += 1
        return nfd(*args, **kwargs)

    def chunks_probe(frame, walk, **options):
        def counted(f, q):
            log["walked"].append(len(q))
            return walk(f, q)
        return chunks(frame, counted, **options)

    monkeypatch.setattr(walk_package.Frame, "__init__", frame_init_probe)
    monkeypatch.setattr(walk_package.Sample, "gather", gather_probe)
    monkeypatch.setattr(gbuffer_module, "normals_from_depth", nfd_probe)
    for module in (walk_module, ssao_module):  # every caller of the chunking machinery
        monkeypatch.setattr(module, "march_chunks", chunks_probe)

    def reset():
        log.update(buffers=[], gathered=[], normals_from_depth=0, walked=[])

    log["reset"] = reset
    return log


def _gbuffer(with_normals=True):
    gb = example_gbuffer(H, W)
    normals = gb.view_normals() if with_normals else None
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=normals, light=gb.light)


def _all_methods():
    return {"tiny": TinyAO, **importable_methods()}


@pytest.mark.parametrize("name", list(_all_methods()))
def test_indirect_and_bent_normals_only_when_asked(name, probe):
    cls = _all_methods()[name]
    gb = _gbuffer()
    kwargs = {"preset": "low"}
    if name == "ssilvb":
        kwargs["indirect"] = False  # SSILVB asks for indirect by default; switched off here
    probe["reset"]()
    out = cls(**kwargs)(gb)
    assert out.indirect is None and out.bent_normal is None and out.ambient is None
    assert all("light" not in b for b in probe["buffers"]), probe["buffers"]
    assert "light" not in probe["gathered"]
    assert probe["normals_from_depth"] == 0  # the G-buffer has normals


def test_indirect_reads_light_when_asked(probe):
    """The positive control: asking for indirect light hands the light buffer over and gathers it (the tensor path:
    a fused kernel gathers the light in its own walk)."""
    cls = importable_methods()["ssilvb"]
    out = cls(preset="low", indirect=True, backend="torch")(_gbuffer())
    assert out.indirect is not None and out.indirect.shape == (1, 3, H, W)
    assert any("light" in b for b in probe["buffers"]) and "light" in probe["gathered"]


@pytest.mark.parametrize("name", ["gtao", "bitmask"])
def test_bent_normals_opt_in(name, probe, monkeypatch):
    cls = importable_methods()[name]
    gb = _gbuffer()
    calls = []
    if name == "gtao":
        import torch_ao.methods.gtao as gtao

        bent = gtao.bent_vector
        monkeypatch.setattr(gtao, "bent_vector", lambda *a, **k: calls.append(1) or bent(*a, **k))
    # (the tensor path: a fused kernel computes the bent normal in its own walk)
    assert cls(preset="low", backend="torch")(gb).bent_normal is None
    off_calls = len(calls)
    out = cls(preset="low", bent_normals=True, backend="torch")(gb)
    assert out.bent_normal is not None and out.bent_normal.shape == (1, 3, H, W)
    if name == "gtao":
        assert off_calls == 0 and len(calls) > 0


def test_normals_from_depth_only_when_missing(probe):
    TinyAO(preset="low")(_gbuffer(with_normals=True))
    assert probe["normals_from_depth"] == 0
    TinyAO(preset="low")(_gbuffer(with_normals=False))
    assert probe["normals_from_depth"] == 1


@pytest.mark.parametrize("name", list(_all_methods()))
def test_background_walks_nothing(name, probe):
    cls = _all_methods()[name]
    frames = background_frames(_gbuffer())
    module = cls(preset="low", backend="torch")  # the tensor walk (the probe counts its pixels)
    # All background: no query pixel, nothing walked, visibility 1 everywhere.
    assert len(walk_package.Frame(frames["empty"]).queries) == 0
    probe["reset"]()
    out = module(frames["empty"])
    assert sum(probe["walked"]) == 0
    assert torch.equal(out.visibility, torch.ones(1, 1, H, W))
    # Half background: exactly half the pixels are walked; background stays 1.
    probe["reset"]()
    out = module(frames["half"])
    assert sum(probe["walked"]) == H * W // 2 == len(walk_package.Frame(frames["half"]).queries)
    assert torch.equal(out.visibility[..., W // 2:], torch.ones(1, 1, H, W - W // 2))
    probe["reset"]()
    module(frames["full"])
    assert sum(probe["walked"]) == H * W


def test_background_scaling_rows():
    rows = background_scaling({"tiny": TinyAO}, "low", gbuffer=_gbuffer(), repeats=1, warmup=0)
    by = {r["frame"]: r for r in rows}
    assert [by[k]["walked_pixels"] for k in ("full", "half", "empty")] == [H * W, H * W // 2, 0]
    assert by["half"]["valid_fraction"] == 0.5 and by["empty"]["background_is_one"] and by["half"]["background_is_one"]
    assert all(r["forward_ms"] > 0 and math.isfinite(r["time_ratio"]) for r in rows)
    with pytest.raises(ValueError, match="no background"):
        background_frames(background_frames(_gbuffer())["half"])

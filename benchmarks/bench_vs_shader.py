"""The CPU targets table: torch_ao's kernels against the SSILVB GLSL article's shader on Mesa llvmpipe, and
their forward+backward against their own forward, in one run.

Frames (``--frames``): ``floor_wall``, a floor meeting a wall (``torch_ao.examples.example_gbuffer``, every
surface given a back face 0.3 world units behind it), and ``room_corner``, the built-in scene's ray-traced
G-buffer (``render_reference(..., backface=True)``: depth, normals, light and the back-face layer, read back
as the reference views are). Each frame at each ``--sizes`` and ``--settings`` (slices x steps per side).

Rows:

* the shader: the article's fragment shader through moderngl's EGL backend exactly as
  ``tests/test_glsl_parity.py`` runs it (view-space position/normal/light as RGBA32F textures), compiled and
  its textures uploaded once; each timed call draws the full-screen quad and reads the result back
  (``fbo.read`` waits for llvmpipe's threads);
* hard forwards without autograd, ``backend="kernel"`` (an uncovered call raises): ``SSILVB(variant=
  "ssilvb_glsl")`` AO + indirect light, ``BitmaskAO`` (uniform, cosine, the ``"hdrp"`` variant, cosine + bent
  normals, the exact union with ``BackfaceThickness`` and ``fetch="edge_aware"``), ``GTAO``, ``HBAO``; ratio to
  the shader;
* forwards + backwards (the loss is the visibility's sum): soft and straight-through ``BitmaskAO`` with
  the gradients of radius and thickness, and with those of depth and normals too (the G-buffer's tensors
  ``requires_grad``); ``GTAO`` and ``HBAO`` with the G-buffer's gradients; ratio to the hard forward of the
  same module (``BitmaskAO`` uniform, ``GTAO``, ``HBAO``) in this run;
* peak memory of each forward + backward at ``--memory-sizes`` (default: the largest size), each case in a
  process of its own (``peak_memory.py``: the peak resident set above the resident size before the call).

Times are the best of ``--repeat`` calls after a warm-up, process CPU time by default (``--clock wall``: wall
time; process time counts llvmpipe's threads too: they run in this process). Machines are noisy: read the
ratios. One table per frame, Markdown, on stdout (progress on stderr):

    LP_NUM_THREADS=1 OMP_NUM_THREADS=1 python benchmarks/bench_vs_shader.py --threads 1 --kernels-only --repeat 3
    python benchmarks/bench_vs_shader.py --sizes 320x180 --settings 4x4 --repeat 2 --threads 1

llvmpipe uses ``LP_NUM_THREADS`` threads (default: the number of cores); torch uses ``--threads``. Without
``--kernels-only`` the tensor-op walk's hard forwards are added (seconds per call).

Before and after: ``--library DIR`` times another checkout's torch_ao with these rows (an earlier commit's
worktree; its kernels build into the ``TORCH_EXTENSIONS_DIR`` you give it), and ``--backend auto`` runs each row
as that library's default would (its kernel where it had one, else its tensor-op walk)::

    git worktree add /tmp/before f6d182b   # the library before the one walk
    TORCH_EXTENSIONS_DIR=/tmp/before_ext LP_NUM_THREADS=1 OMP_NUM_THREADS=1 python benchmarks/bench_vs_shader.py \
        --library /tmp/before --backend auto --threads 1 --kernels-only --repeat 3 --cases ... > before.md

and ``benchmarks/before_after.py before.md after.md`` merges it with this library's run, cell by cell.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "glsl"))


def _library(argv: list[str]) -> Path:
    """The torch_ao checkout to time: ``--library DIR`` (read before anything imports torch_ao), else this one."""
    for i, arg in enumerate(argv):
        if arg == "--library" and i + 1 < len(argv):
            return Path(argv[i + 1]).resolve()
        if arg.startswith("--library="):
            return Path(arg.split("=", 1)[1]).resolve()
    return ROOT


LIBRARY = _library(sys.argv[1:])
sys.path.insert(0, str(LIBRARY))  # that checkout's torch_ao, not an installed copy
#: the backend of the kernel rows: "kernel" (an uncovered call raises), or "auto" with --backend auto (an
#: earlier library's rows: a kernel where it had one, else its tensor path)
KERNEL_BACKEND = "kernel"

FRAMES = {"floor_wall": "a floor meeting a wall (`torch_ao.examples.example_gbuffer`, back faces 0.3 behind)",
          "room_corner": "the `room_corner` scene (floor, two walls, boxes; ray-traced G-buffer with its back-face layer)"}


class ShaderRun:
    """The shader compiled and its textures uploaded once; ``__call__`` draws and reads back."""

    def __init__(self, ctx, gbuffer, *, slices: int, steps: int, radius: float, thickness: float) -> None:
        import moderngl
        from runner import HERE, SHADERS, _rgba

        H, W = gbuffer.depth.shape[-2:]
        self.ctx = ctx
        self.prog = ctx.program(vertex_shader=(HERE / "quad.vert").read_text(),
                                fragment_shader=(HERE / SHADERS["jitter"]).read_text())
        images = {"screenPosition": gbuffer.positions()[0], "screenNormal": gbuffer.view_normals()[0],
                  "screenLight": gbuffer.light[0]}
        self.textures = []
        for unit, (name, img) in enumerate(images.items()):
            tex = ctx.texture((W, H), 4, _rgba(img), dtype="f4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
            tex.use(unit)
            self.textures.append(tex)
            if name in self.prog:
                self.prog[name] = unit
        uniforms = {"sampleCount": float(steps), "sampleRadius": float(radius), "sliceCount": float(slices),
                    "hitThickness": float(thickness), "screenSize": (float(W), float(H))}
        for name, value in uniforms.items():
            if name in self.prog:
                self.prog[name] = value
        if "projection" in self.prog:
            P = gbuffer.camera.opengl_projection()[0].to(torch.float32).numpy()
            self.prog["projection"].write(np.ascontiguousarray(P.T, dtype="f4").tobytes())
        self.vbo = ctx.buffer(np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4").tobytes())
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "2f", "in_vert")])
        self.fbo = ctx.framebuffer([ctx.texture((W, H), 4, dtype="f4")])
        self.size = (W, H)
        self.mode = moderngl.TRIANGLE_STRIP

    def __call__(self) -> bytes:
        for unit, tex in enumerate(self.textures):
            tex.use(unit)
        self.fbo.use()
        self.ctx.viewport = (0, 0, *self.size)
        self.vao.render(self.mode)
        return self.fbo.read(components=4, dtype="f4")

    def release(self) -> None:
        for obj in (*self.textures, self.fbo, self.vao, self.vbo, self.prog):
            obj.release()


# ------------------------------------------------------------------ the cases

@dataclass(frozen=True)
class Case:
    """One row: ``make(settings)`` builds the module; ``gradients``: ``None`` (a forward under ``no_grad``),
    ``"parameters"`` (radius and thickness) or ``"gbuffer"`` (depth and normals, and the parameters);
    ``against``: ``"shader"`` or the key of the hard forward this row is a multiple of; ``target``: the ratio
    the project aims at (at most)."""

    label: str
    make: Callable[[dict], torch.nn.Module]
    gradients: str | None
    against: str
    target: float
    kernel: bool = True


def _without_thickness(settings: dict) -> dict:
    return {k: v for k, v in settings.items() if k != "thickness"}


def _cases() -> dict[str, Case]:
    import torch_ao
    from torch_ao.thickness import BackfaceThickness
    from torch_ao.thickness_net import NetThickness

    def bitmask(backend=KERNEL_BACKEND, **options):
        return lambda s: torch_ao.BitmaskAO(backend=backend, **s, **options)

    def horizon(cls, backend=KERNEL_BACKEND, **options):
        return lambda s: cls(backend=backend, **_without_thickness(s), **options)

    def ue4_ssao(s):  # (its directions evenly spaced, as many as the shader's slices)
        return torch_ao.UE4SSAO(sample_set="uniform", backend=KERNEL_BACKEND, **_without_thickness(s))

    def pssao(s):  # (the gist's pixel offsets: no radius)
        return torch_ao.PSSAO(slices=s["slices"], steps=s["steps"], backend=KERNEL_BACKEND)

    def backface(backend):
        return lambda s: torch_ao.BitmaskAO(mode="soft", weighting="cosine", fetch="edge_aware", backend=backend,
                                            thickness=BackfaceThickness(0.8, 0.15), **_without_thickness(s))

    def net(backend):
        def make(s):
            torch.manual_seed(0)  # (the net's initial weights)
            return torch_ao.BitmaskAO(mode="soft", weighting="cosine", fetch="edge_aware", backend=backend,
                                      thickness=NetThickness(scale=s["radius"], init=0.3), **_without_thickness(s))
        return make

    def exact(backend, trainable=False):
        return lambda s: torch_ao.BitmaskAO(variant="exact", thickness=BackfaceThickness(), fetch="edge_aware",
                                            trainable=trainable, backend=backend, **_without_thickness(s))

    return {
        "ssilvb_glsl": Case("`ssilvb_glsl` hard AO + indirect", lambda s: torch_ao.SSILVB(
            variant="ssilvb_glsl", mode="hard", backend=KERNEL_BACKEND, **s), None, "shader", 1.0),
        "bitmask": Case("`BitmaskAO` hard", bitmask(mode="hard"), None, "shader", 1.0),
        "cosine": Case("`BitmaskAO` hard, cosine", bitmask(mode="hard", weighting="cosine"), None, "shader", 1.0),
        "bitmask_hdrp": Case("`BitmaskAO` hard, variant `hdrp`", bitmask(mode="hard", variant="hdrp"), None, "shader",
                             1.0),
        "cosine_bent": Case("`BitmaskAO` hard, cosine + bent normals",
                            bitmask(mode="hard", weighting="cosine", bent_normals=True), None, "shader", 1.0),
        "exact": Case("`BitmaskAO` exact + `BackfaceThickness` + edge-aware fetch", exact(KERNEL_BACKEND), None, "shader", 1.0),
        "gtao": Case("`GTAO`", horizon(torch_ao.GTAO), None, "shader", 1.0),
        "hbao": Case("`HBAO`", horizon(torch_ao.HBAO), None, "shader", 1.0),
        "gtao_edge": Case("`GTAO` edge-aware fetch", horizon(torch_ao.GTAO, fetch="edge_aware"), None, "shader", 1.0),
        "gtao_projected": Case("`GTAO`, slices drawn by the projected normal's density",
                               horizon(torch_ao.GTAO, slice_sampling="projected_normal"), None, "shader", 1.0),
        "ssilvb_glsl_torch": Case("`ssilvb_glsl`, tensor ops", lambda s: torch_ao.SSILVB(
            variant="ssilvb_glsl", mode="hard", backend="torch", **s), None, "shader", 1.0, kernel=False),
        "bitmask_torch": Case("`BitmaskAO` hard, tensor ops", bitmask("torch", mode="hard"), None, "shader", 1.0,
                              kernel=False),
        "exact_torch": Case("`BitmaskAO` exact + back-face + edge-aware, tensor ops", exact("torch"), None, "shader",
                            1.0, kernel=False),
        "gtao_torch": Case("`GTAO`, tensor ops", horizon(torch_ao.GTAO, "torch"), None, "shader", 1.0, kernel=False),
        "gtao_projected_torch": Case("`GTAO`, slices drawn by the projected normal's density, tensor ops",
                                     horizon(torch_ao.GTAO, "torch", slice_sampling="projected_normal"), None, "shader",
                                     1.0, kernel=False),
        "soft_parameters": Case("soft `BitmaskAO` fwd+bwd, radius + thickness", bitmask(mode="soft"),
                                "parameters", "bitmask", 3.0),
        "soft_gbuffer": Case("soft `BitmaskAO` fwd+bwd, depth + normals", bitmask(mode="soft"),
                             "gbuffer", "bitmask", 3.0),
        "straight_parameters": Case("straight-through `BitmaskAO` fwd+bwd, radius + thickness",
                                    bitmask(mode="straight_through"), "parameters", "bitmask", 3.0),
        "straight_gbuffer": Case("straight-through `BitmaskAO` fwd+bwd, depth + normals",
                                 bitmask(mode="straight_through"), "gbuffer", "bitmask", 3.0),
        "cosine_edge_gbuffer": Case("soft `BitmaskAO` cosine + edge-aware fwd+bwd, depth + normals",
                                    bitmask(mode="soft", weighting="cosine", fetch="edge_aware"), "gbuffer", "bitmask",
                                    3.0),
        "cosine_edge_gbuffer_torch": Case(
            "soft `BitmaskAO` cosine + edge-aware fwd+bwd, depth + normals, tensor ops",
            bitmask("torch", mode="soft", weighting="cosine", fetch="edge_aware"),
            "gbuffer", "bitmask", 3.0, kernel=False),
        # torch-ao fit's default pipeline (cosine, the back-face layer near its fitted scale and offset, edge-aware)
        "backface_gbuffer": Case("soft `BitmaskAO` cosine + back-face + edge-aware fwd+bwd, depth + normals",
                                 backface(KERNEL_BACKEND), "gbuffer", "bitmask", 3.0),
        "backface_parameters": Case("soft `BitmaskAO` cosine + back-face + edge-aware fwd+bwd, radius + thickness",
                                    backface(KERNEL_BACKEND), "parameters", "bitmask", 3.0),
        "backface_gbuffer_torch": Case(
            "soft `BitmaskAO` cosine + back-face + edge-aware fwd+bwd, depth + normals, tensor ops",
            backface("torch"), "gbuffer", "bitmask", 3.0, kernel=False),
        # the learned thickness trained end to end (training_examples/train_thickness_net.py --finetune-epochs)
        "net_parameters": Case("soft `BitmaskAO` cosine + `NetThickness` + edge-aware fwd+bwd, the net's weights",
                               net(KERNEL_BACKEND), "parameters", "bitmask", 3.0),
        "net_parameters_torch": Case(
            "soft `BitmaskAO` cosine + `NetThickness` + edge-aware fwd+bwd, the net's weights, tensor ops",
            net("torch"), "parameters", "bitmask", 3.0, kernel=False),
        "cosine_hard_gbuffer": Case("`BitmaskAO` hard, cosine fwd+bwd, depth + normals",
                                    bitmask(mode="hard", weighting="cosine"), "gbuffer", "cosine", 3.0),
        "cosine_bent_hard_gbuffer": Case("`BitmaskAO` hard, cosine + bent normals fwd+bwd, depth + normals",
                                         bitmask(mode="hard", weighting="cosine", bent_normals=True), "gbuffer",
                                         "cosine_bent", 3.0),
        "cosine_hard_gbuffer_torch": Case(
            "`BitmaskAO` hard, cosine fwd+bwd, depth + normals, tensor ops",
            bitmask("torch", mode="hard", weighting="cosine"),
            "gbuffer", "cosine", 3.0, kernel=False),
        "cosine_hdrp": Case("`BitmaskAO` hard, variant `hdrp`, cosine",
                            bitmask(mode="hard", variant="hdrp", weighting="cosine"), None, "shader", 1.0),
        "bitmask_hdrp_gbuffer": Case("`BitmaskAO` hard, variant `hdrp`, cosine fwd+bwd, depth + normals",
                                     bitmask(mode="hard", variant="hdrp", weighting="cosine"), "gbuffer",
                                     "cosine_hdrp", 3.0),
        "bitmask_hdrp_gbuffer_torch": Case(
            "`BitmaskAO` hard, variant `hdrp`, cosine fwd+bwd, depth + normals, tensor ops",
            bitmask("torch", mode="hard", variant="hdrp", weighting="cosine"),
            "gbuffer", "cosine_hdrp", 3.0, kernel=False),
        "soft_hdrp_parameters": Case("soft `BitmaskAO`, variant `hdrp` fwd+bwd, radius + thickness",
                                     bitmask(mode="soft", variant="hdrp"), "parameters", "bitmask_hdrp", 3.0),
        "soft_hdrp_parameters_torch": Case(
            "soft `BitmaskAO`, variant `hdrp` fwd+bwd, radius + thickness, tensor ops",
            bitmask("torch", mode="soft", variant="hdrp"), "parameters",
            "bitmask_hdrp", 3.0, kernel=False),
        "soft_hdrp_gbuffer": Case("soft `BitmaskAO`, variant `hdrp` fwd+bwd, depth + normals",
                                  bitmask(mode="soft", variant="hdrp"), "gbuffer", "bitmask_hdrp", 3.0),
        "soft_hdrp_gbuffer_torch": Case(
            "soft `BitmaskAO`, variant `hdrp` fwd+bwd, depth + normals, tensor ops",
            bitmask("torch", mode="soft", variant="hdrp"), "gbuffer",
            "bitmask_hdrp", 3.0, kernel=False),
        # a thickness growth, the shader with the back-face layer, a soft ambient colour
        "bitmask_growth": Case("`BitmaskAO` hard, thickness growth 0.5", bitmask(mode="hard", thickness_growth=0.5),
                               None, "shader", 1.0),
        "bitmask_growth_torch": Case("`BitmaskAO` hard, thickness growth 0.5, tensor ops",
                                     bitmask("torch", mode="hard", thickness_growth=0.5), None, "shader", 1.0,
                                     kernel=False),
        "soft_growth_parameters": Case("soft `BitmaskAO`, thickness growth 0.5 fwd+bwd, radius + thickness + growth",
                                       bitmask(mode="soft", thickness_growth=0.5), "parameters", "bitmask", 3.0),
        "soft_growth_parameters_torch": Case(
            "soft `BitmaskAO`, thickness growth 0.5 fwd+bwd, radius + thickness + growth, tensor ops",
            bitmask("torch", mode="soft", thickness_growth=0.5), "parameters", "bitmask", 3.0, kernel=False),
        "soft_growth_gbuffer": Case("soft `BitmaskAO`, thickness growth 0.5 fwd+bwd, depth + normals",
                                    bitmask(mode="soft", thickness_growth=0.5), "gbuffer", "bitmask", 3.0),
        "ssilvb_glsl_backface": Case("`ssilvb_glsl` hard AO + indirect, `BackfaceThickness`", lambda s: torch_ao.SSILVB(
            variant="ssilvb_glsl", mode="hard", backend=KERNEL_BACKEND, thickness=BackfaceThickness(0.8, 0.15),
            **_without_thickness(s)), None, "shader", 1.0),
        "ssilvb_glsl_backface_torch": Case(
            "`ssilvb_glsl` hard AO + indirect, `BackfaceThickness`, tensor ops", lambda s: torch_ao.SSILVB(
                variant="ssilvb_glsl", mode="hard", backend="torch", thickness=BackfaceThickness(0.8, 0.15),
                **_without_thickness(s)), None, "shader", 1.0, kernel=False),
        "soft_ambient_gbuffer": Case("soft `BitmaskAO` + ambient colour fwd+bwd, depth + normals",
                                     bitmask(mode="soft", ambient=(0.2, 0.5, 1.0)), "gbuffer", "bitmask", 3.0),
        "soft_bent_gbuffer": Case("soft `BitmaskAO` + bent normals fwd+bwd, depth + normals",
                                  bitmask(mode="soft", bent_normals=True), "gbuffer", "bitmask", 3.0),
        "soft_bent_gbuffer_torch": Case("soft `BitmaskAO` + bent normals fwd+bwd, depth + normals, tensor ops",
                                        bitmask("torch", mode="soft", bent_normals=True), "gbuffer", "bitmask", 3.0,
                                        kernel=False),
        "ssilvb_soft_gbuffer": Case("soft `SSILVB` (AO + indirect) fwd+bwd, depth + normals", lambda s: torch_ao.SSILVB(
            mode="soft", backend=KERNEL_BACKEND, **s), "gbuffer", "bitmask", 3.0),
        "ssilvb_soft_gbuffer_torch": Case(
            "soft `SSILVB` (AO + indirect) fwd+bwd, depth + normals, tensor ops", lambda s: torch_ao.SSILVB(
                mode="soft", backend="torch", **s), "gbuffer", "bitmask", 3.0, kernel=False),
        "ssilvb_cosine": Case("`SSILVB` hard, cosine (AO + indirect light)", lambda s: torch_ao.SSILVB(
            mode="hard", weighting="cosine", backend=KERNEL_BACKEND, **s), None, "shader", 1.0),
        "ssilvb_cosine_gbuffer": Case("`SSILVB` hard, cosine fwd+bwd, depth + normals", lambda s: torch_ao.SSILVB(
            mode="hard", weighting="cosine", backend=KERNEL_BACKEND, **s), "gbuffer", "ssilvb_cosine", 3.0),
        "ssilvb_cosine_gbuffer_torch": Case(
            "`SSILVB` hard, cosine fwd+bwd, depth + normals, tensor ops", lambda s: torch_ao.SSILVB(
                mode="hard", weighting="cosine", backend="torch", **s), "gbuffer", "ssilvb_cosine", 3.0, kernel=False),
        "ssilvb_glsl_gbuffer": Case("`ssilvb_glsl` hard AO + indirect fwd+bwd, depth + normals",
                                    lambda s: torch_ao.SSILVB(variant="ssilvb_glsl", mode="hard", backend=KERNEL_BACKEND, **s),
                                    "gbuffer", "ssilvb_glsl", 3.0),
        "ssilvb_glsl_gbuffer_torch": Case(
            "`ssilvb_glsl` hard AO + indirect fwd+bwd, depth + normals, tensor ops", lambda s: torch_ao.SSILVB(
                variant="ssilvb_glsl", mode="hard", backend="torch", **s), "gbuffer", "ssilvb_glsl", 3.0, kernel=False),
        "ssilvb_glsl_soft_gbuffer": Case("soft `ssilvb_glsl` AO + indirect fwd+bwd, depth + normals",
                                         lambda s: torch_ao.SSILVB(variant="ssilvb_glsl", mode="soft", backend=KERNEL_BACKEND,
                                                                   **s), "gbuffer", "ssilvb_glsl", 3.0),
        "ssilvb_glsl_soft_gbuffer_torch": Case(
            "soft `ssilvb_glsl` AO + indirect fwd+bwd, depth + normals, tensor ops", lambda s: torch_ao.SSILVB(
                variant="ssilvb_glsl", mode="soft", backend="torch", **s), "gbuffer", "ssilvb_glsl", 3.0, kernel=False),
        "exact_parameters": Case("`BitmaskAO` exact + back-face + edge-aware fwd+bwd, radius + thickness + scale",
                                 exact(KERNEL_BACKEND, trainable=True), "parameters", "exact", 3.0),
        "exact_gbuffer": Case("`BitmaskAO` exact + back-face + edge-aware fwd+bwd, depth + normals",
                              exact(KERNEL_BACKEND, trainable=True), "gbuffer", "exact", 3.0),
        "exact_gbuffer_torch": Case("`BitmaskAO` exact + back-face + edge-aware fwd+bwd, depth + normals, tensor ops",
                                    exact("torch", trainable=True), "gbuffer", "exact", 3.0, kernel=False),
        "gtao_gbuffer": Case("`GTAO` fwd+bwd, depth + normals", horizon(torch_ao.GTAO), "gbuffer", "gtao", 3.0),
        "gtao_edge_gbuffer": Case("`GTAO` edge-aware fetch fwd+bwd, depth + normals",
                                  horizon(torch_ao.GTAO, fetch="edge_aware"), "gbuffer", "gtao_edge", 3.0),
        "hbao_gbuffer": Case("`HBAO` fwd+bwd, depth + normals", horizon(torch_ao.HBAO), "gbuffer", "hbao", 3.0),
        "gtao_projected_gbuffer": Case("`GTAO`, slices drawn by the projected normal's density, fwd+bwd, depth + "
                                       "normals", horizon(torch_ao.GTAO, slice_sampling="projected_normal"), "gbuffer",
                                       "gtao_projected", 3.0),
        "soft_projected_gbuffer": Case("soft `BitmaskAO`, slices drawn by the projected normal's density, fwd+bwd, "
                                       "depth + normals", bitmask(mode="soft", slice_sampling="projected_normal"),
                                       "gbuffer", "bitmask", 3.0),
        "soft_projected_gbuffer_torch": Case(
            "soft `BitmaskAO`, slices drawn by the projected normal's density, fwd+bwd, depth + normals, tensor ops",
            bitmask("torch", mode="soft", slice_sampling="projected_normal"), "gbuffer", "bitmask", 3.0, kernel=False),
        "cosine_projected_gbuffer": Case("`BitmaskAO` hard, cosine, slices drawn by the projected normal's density, "
                                         "fwd+bwd, depth + normals",
                                         bitmask(mode="hard", weighting="cosine", slice_sampling="projected_normal"),
                                         "gbuffer", "cosine", 3.0),
        "ue4_ssao": Case("`UE4SSAO` (uniform directions)", ue4_ssao, None, "shader", 1.0),
        "ue4_ssao_gbuffer": Case("`UE4SSAO` fwd+bwd, depth + normals", ue4_ssao, "gbuffer", "ue4_ssao", 3.0),
        "pssao": Case("`PSSAO`", pssao, None, "shader", 1.0),
        "pssao_gbuffer": Case("`PSSAO` fwd+bwd, depth + normals", pssao, "gbuffer", "pssao", 3.0),
    }


def frame_gbuffer(frame: str, height: int, width: int, cache: Path | None = None):
    """The frame's G-buffer at ``height x width``. ``room_corner`` is ray traced once and kept as a reference
    file in ``cache`` (the memory cases' processes read it back)."""
    import torch_ao
    from torch_ao.io import load_gbuffer

    if frame == "floor_wall":
        from torch_ao.examples import example_gbuffer

        gb = example_gbuffer(height, width)
        # every surface 0.3 world units thick (the back-face model's cost does not depend on the values)
        return torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=gb.light,
                                backface_depth=gb.depth + 0.3)
    if frame != "room_corner":
        raise ValueError(f"--frames: expected floor_wall or room_corner, got {frame!r}")
    path = (cache or Path(tempfile.gettempdir())) / f"room_corner_{width}x{height}.npz"
    if not path.exists():
        from torch_ao.reference import get_scene, render_reference

        ref = render_reference(get_scene("room_corner"), height=height, width=width, spp=2, uniform=False,
                               progress=False, backface=True)
        ref.save(path)
    return load_gbuffer(path)[0]


def with_gradients(gbuffer, gradients: str | None):
    """The G-buffer whose depth and normals require gradients (``gradients == "gbuffer"``), else itself."""
    if gradients != "gbuffer":
        return gbuffer
    import torch_ao

    return torch_ao.GBuffer(depth=gbuffer.depth.detach().clone().requires_grad_(True), camera=gbuffer.camera,
                            normals=gbuffer.normals.detach().clone().requires_grad_(True), light=gbuffer.light,
                            mask=gbuffer.mask, backface_depth=gbuffer.backface_depth)


def case_call(case: Case, gbuffer, settings: dict) -> Callable[[], None]:
    """One call of the case: the forward under ``no_grad``, or forward + backward of its outputs' sum."""
    module = case.make(settings)
    if case.gradients is None:
        def forward():
            with torch.no_grad():
                module(gbuffer)
        return forward
    gb = with_gradients(gbuffer, case.gradients)
    leaves = [gb.depth, gb.normals] if case.gradients == "gbuffer" else []
    if not any(p.requires_grad for p in module.parameters()):
        raise ValueError(f"{case.label}: the module has no trainable parameter")

    def forward_backward():
        module.zero_grad(set_to_none=True)
        for x in leaves:
            x.grad = None
        out = module(gb)
        outputs = (out.visibility, out.indirect, out.ambient, out.bent_normal)
        sum(value.sum() for value in outputs if value is not None).backward()
    return forward_backward


def best_ms(fn, repeat: int) -> tuple[float, float]:
    """Best wall and best CPU milliseconds of ``repeat`` calls after a warm-up (CPU: process time)."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * min(wall), 1e3 * min(cpu)


# ------------------------------------------------------------------ peak memory, one process per case

def memory_child(spec: dict) -> dict:
    from peak_memory import PeakMemory

    global KERNEL_BACKEND
    KERNEL_BACKEND = spec["backend"]
    torch.set_num_threads(spec["threads"])
    gbuffer = frame_gbuffer(spec["frame"], spec["height"], spec["width"], Path(spec["cache"]))
    call = case_call(_cases()[spec["case"]], gbuffer, spec["settings"])
    with PeakMemory() as peak:
        call()
    return {"peak_mb": peak.mb, "baseline_mb": peak.baseline_mb}


def peak_mb(**spec) -> float:
    cmd = [sys.executable, __file__, "--library", str(LIBRARY), "--memory-child", json.dumps(spec)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"memory of {spec['case']} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])["peak_mb"]


# ------------------------------------------------------------------ the table

def _size_label(size: tuple[int, int], setting: tuple[int, int]) -> str:
    return f"{size[0]}×{size[1]}, {setting[0]} × {setting[1]}"


def _ms(ms: float) -> str:
    return f"{ms:.0f}" if ms < 10_000 else f"{ms / 1e3:.1f} s"


def frame_table(frame: str, cases: dict[str, Case], columns: list, shader: dict, times: dict, memory: dict,
                memory_columns: list, clock: str) -> str:
    """Markdown: a row per case, a column per (size, setting); a cell is ``ms (ratio)``, the ratio in bold where
    it misses the target; the peak memory of the forward+backward rows last (target: at most 1 GB)."""
    head = ["case", "target"] + [_size_label(*c) for c in columns]
    if memory_columns:
        by_size = {}
        for size, setting in memory_columns:
            by_size.setdefault(size, []).append(f"{setting[0]} × {setting[1]}")
        head.append("peak MB of fwd+bwd (≤ 1024), " + "; ".join(f"{W}×{H}: " + " / ".join(s)
                                                                 for (W, H), s in by_size.items()))
    lines = [f"**{FRAMES[frame]}**, {'CPU' if clock == 'cpu' else 'wall'} ms (ratio)", "", "| " + " | ".join(head) + " |",
             "|---|---|" + "---:|" * (len(head) - 2)]
    cells = [f"{_ms(shader[c])}" for c in columns]
    lines.append("| shader on llvmpipe | | " + " | ".join(cells) + (" | |" if memory_columns else " |"))
    for key, case in cases.items():
        against = "the shader" if case.against == "shader" else cases[case.against].label
        row = [case.label, f"≤ {case.target:g}× {against}"]
        for c in columns:
            ms = times[key, c]
            base = shader[c] if case.against == "shader" else times[case.against, c]
            ratio = f"{ms / base:.2f}×"
            ratio = ratio if float(ratio[:-1]) <= case.target else f"**{ratio}**"
            row.append(f"{_ms(ms)} ({ratio})")
        if memory_columns:
            row.append(" / ".join(f"{memory[key, c]:.0f}" for c in memory_columns) if case.gradients else "")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _pairs(values: list[str], sep: str) -> list[tuple[int, int]]:
    return [tuple(int(v) for v in value.lower().split(sep.lower())) for value in values]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--memory-child", help=argparse.SUPPRESS)
    ap.add_argument("--frames", nargs="+", default=list(FRAMES), choices=list(FRAMES), help="frames (default: both)")
    ap.add_argument("--sizes", nargs="+", default=["640x360", "1280x720"], help="WxH frame sizes")
    ap.add_argument("--settings", nargs="+", default=["4x4", "4x8"], help="SLICESxSTEPS sample counts")
    ap.add_argument("--radius", type=float, default=1.0, help="sample radius, world units")
    ap.add_argument("--thickness", type=float, default=0.5, help="hit thickness, world units")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per case (best is reported)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--clock", choices=["cpu", "wall"], default="cpu", help="the time tabled and divided")
    ap.add_argument("--kernels-only", action="store_true", help="leave out the tensor-op rows (seconds per call)")
    ap.add_argument("--cases", nargs="+", default=None, metavar="CASE",
                    help="only these rows (default: all): " + ", ".join(_cases()))
    ap.add_argument("--memory-sizes", nargs="*", default=None,
                    help="WxH sizes (of --sizes) whose forward+backward peak memory is measured (default: the "
                         "largest; the flag alone: no memory column)")
    ap.add_argument("--library", default=str(ROOT), metavar="DIR",
                    help="the torch_ao checkout to time (default: this one; an earlier commit's worktree gives the "
                         "'before' of a before/after table)")
    ap.add_argument("--backend", choices=["kernel", "auto"], default="kernel",
                    help="the kernel rows' backend: kernel (an uncovered call raises) or auto (a kernel where the "
                         "library has one, else its tensor path: an earlier library's rows)")
    args = ap.parse_args(argv)
    global KERNEL_BACKEND
    KERNEL_BACKEND = args.backend
    if args.memory_child:
        print(json.dumps(memory_child(json.loads(args.memory_child))))
        return 0

    from runner import create_context

    sizes, settings = _pairs(args.sizes, "x"), _pairs(args.settings, "x")
    memory_sizes = [max(sizes, key=lambda s: s[0] * s[1])] if args.memory_sizes is None else _pairs(args.memory_sizes, "x")
    if not set(memory_sizes) <= set(sizes):
        ap.error("--memory-sizes: expected sizes of --sizes")
    torch.set_num_threads(args.threads)
    ctx = create_context()
    print(f"shader: {ctx.info['GL_RENDERER']} (LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'default')}); "
          f"torch {torch.__version__}, {args.threads} threads; best of {args.repeat}, {args.clock} time; "
          f"torch_ao from {LIBRARY}, backend {args.backend}", flush=True)
    cases = {k: c for k, c in _cases().items() if c.kernel or not args.kernels_only}
    if args.cases:
        unknown = sorted(set(args.cases) - set(_cases()))
        if unknown:
            ap.error(f"--cases: unknown {', '.join(unknown)}; expected some of {', '.join(_cases())}")
        # a row that is a multiple of another keeps that other row
        wanted = set(args.cases) | {cases[k].against for k in args.cases if k in cases and cases[k].against != "shader"}
        cases = {k: c for k, c in cases.items() if k in wanted}
    columns = [(size, setting) for size in sizes for setting in settings]
    memory_columns = [c for c in columns if c[0] in memory_sizes]
    clock = 1 if args.clock == "cpu" else 0
    cache = Path(tempfile.mkdtemp(prefix="bench_vs_shader_"))
    for frame in args.frames:
        shader, times, memory = {}, {}, {}
        for size in sizes:
            W, H = size
            gb = frame_gbuffer(frame, H, W, cache)
            for setting in settings:
                column = (size, setting)
                common = dict(slices=setting[0], steps=setting[1], radius=args.radius, thickness=args.thickness)
                run = ShaderRun(ctx, gb, **common)
                shader[column] = best_ms(run, args.repeat)[clock]
                run.release()
                print(f"{frame} {_size_label(*column)}: shader {shader[column]:.0f} ms", file=sys.stderr, flush=True)
                for key, case in cases.items():
                    times[key, column] = best_ms(case_call(case, gb, common), args.repeat)[clock]
                    line = f"{frame} {_size_label(*column)}: {case.label} {times[key, column]:.0f} ms"
                    if case.gradients and column in memory_columns:
                        memory[key, column] = peak_mb(case=key, frame=frame, height=H, width=W, settings=common,
                                                      threads=args.threads, cache=str(cache), backend=args.backend)
                        line += f", peak {memory[key, column]:.0f} MB"
                    print(line, file=sys.stderr, flush=True)
        print()
        print(frame_table(frame, cases, columns, shader, times, memory, memory_columns, args.clock), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

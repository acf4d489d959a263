"""The SSILVB GLSL article's shader on Mesa llvmpipe against torch_ao, side by side in one process.

Same G-buffer (``torch_ao.examples.example_gbuffer``: a floor meeting a wall), same settings. The
shader runs through moderngl's EGL backend exactly as ``tests/test_glsl_parity.py`` runs it (view-space
position/normal/light as RGBA32F textures); it is compiled and its textures uploaded once, then each
timed call draws the full-screen quad and reads the result back (``fbo.read`` waits for the GPU, here
llvmpipe's threads). torch_ao's calls are whole module forwards without autograd (``SSILVB(variant="ssilvb_glsl")``, the
shader's own rules, ``BitmaskAO`` and ``GTAO`` each twice: the fused kernel, ``backend="kernel"``, and the
tensor-op walk, ``backend="torch"``). Best of ``--repeat``
calls after a warm-up, wall and CPU (process) time; machines are noisy, so read the ratios.

    python benchmarks/bench_vs_shader.py                       # 640x360 and 1280x720, 4x4 and 4x8
    python benchmarks/bench_vs_shader.py --sizes 320x180 --repeat 3 --threads 1

llvmpipe uses ``LP_NUM_THREADS`` threads (default: the number of cores); torch uses ``--threads``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "glsl"))
sys.path.insert(0, str(ROOT))  # this checkout's torch_ao, not an installed copy


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


def best_ms(fn, repeat: int) -> tuple[float, float]:
    """Best wall and best CPU milliseconds of ``repeat`` calls after a warm-up (CPU: process time, which
    counts llvmpipe's threads too: they run in this process)."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * min(wall), 1e3 * min(cpu)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["640x360", "1280x720"], help="WxH frame sizes")
    ap.add_argument("--settings", nargs="+", default=["4x4", "4x8"], help="SLICESxSTEPS sample counts")
    ap.add_argument("--radius", type=float, default=1.0, help="sample radius, world units")
    ap.add_argument("--thickness", type=float, default=0.5, help="hit thickness, world units")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per case (best is reported)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--kernels-only", action="store_true", help="leave out the tensor-op columns (seconds per call)")
    args = ap.parse_args(argv)

    import torch_ao
    from runner import create_context
    from torch_ao.examples import example_gbuffer

    torch.set_num_threads(args.threads)
    ctx = create_context()
    print(f"shader: {ctx.info['GL_RENDERER']} (LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'default')}); "
          f"torch {torch.__version__}, {args.threads} threads")
    # (column, kernel?, module factory); the tensor-op columns take seconds per call
    columns = [
        ("ssilvb_glsl hard AO+indirect, kernel", True,
         lambda c: torch_ao.SSILVB(variant="ssilvb_glsl", mode="hard", backend="kernel", **c)),
        ("ssilvb_glsl, tensor ops", False, lambda c: torch_ao.SSILVB(variant="ssilvb_glsl", mode="hard", backend="torch", **c)),
        ("BitmaskAO hard AO, kernel", True, lambda c: torch_ao.BitmaskAO(mode="hard", backend="kernel", **c)),
        ("BitmaskAO hard AO, tensor ops", False, lambda c: torch_ao.BitmaskAO(mode="hard", backend="torch", **c)),
        ("BitmaskAO cosine hard AO, kernel", True,
         lambda c: torch_ao.BitmaskAO(mode="hard", weighting="cosine", backend="kernel", **c)),
        ("BitmaskAO cosine hard AO + bent normals, kernel", True,
         lambda c: torch_ao.BitmaskAO(mode="hard", weighting="cosine", bent_normals=True, backend="kernel", **c)),
        ("BitmaskAO exact + back-face + edge_aware, kernel", True,
         lambda c: torch_ao.BitmaskAO(variant="exact", thickness=torch_ao.thickness.BackfaceThickness(), trainable=False,
                                      backend="kernel", **{k: v for k, v in c.items() if k != "thickness"})),
        ("BitmaskAO exact + back-face + edge_aware, tensor ops", False,
         lambda c: torch_ao.BitmaskAO(variant="exact", thickness=torch_ao.thickness.BackfaceThickness(), trainable=False,
                                      backend="torch", **{k: v for k, v in c.items() if k != "thickness"})),
        ("GTAO, kernel", True, lambda c: torch_ao.GTAO(backend="kernel", **{k: v for k, v in c.items() if k != "thickness"})),
        ("GTAO, tensor ops", False, lambda c: torch_ao.GTAO(backend="torch", **{k: v for k, v in c.items() if k != "thickness"})),
        ("HBAO, kernel", True, lambda c: torch_ao.HBAO(backend="kernel", **{k: v for k, v in c.items() if k != "thickness"})),
    ]
    columns = [col for col in columns if col[1] or not args.kernels_only]
    print("| size, slices x steps | shader on llvmpipe (ms) | " + " | ".join(col[0] for col in columns) + " |")
    print("|---|---:|" + "---:|" * len(columns))
    for size in args.sizes:
        W, H = map(int, size.split("x"))
        gb = example_gbuffer(H, W)
        # a back-face layer for the exact pipeline: every surface 0.3 world units thick (its cost does not
        # depend on the values)
        gb = torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=gb.light,
                              backface_depth=gb.depth + 0.3)
        for setting in args.settings:
            slices, steps = map(int, setting.split("x"))
            shader = ShaderRun(ctx, gb, slices=slices, steps=steps, radius=args.radius, thickness=args.thickness)
            ms_shader, cpu_shader = best_ms(shader, args.repeat)
            common = dict(slices=slices, steps=steps, radius=args.radius, thickness=args.thickness)
            cells = []
            with torch.no_grad():
                for _, _, make in columns:
                    module = make(common)
                    ms, cpu = best_ms(lambda: module(gb), args.repeat)
                    cells.append(f"{ms:.0f} ms ({ms / ms_shader:.1f}x; CPU {cpu:.0f}, {cpu / cpu_shader:.1f}x)")
            print(f"| {W}x{H}, {slices} x {steps} | {ms_shader:.0f} (CPU {cpu_shader:.0f}) | " + " | ".join(cells) + " |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

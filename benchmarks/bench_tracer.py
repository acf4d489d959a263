"""Ray-tracer speed: rays per second (torch on analytic scenes, Embree and torch on meshes) and the
time of full references. Run: ``python benchmarks/bench_tracer.py [--quick] [--device cuda]``.

``--large [TRIANGLES]`` instead times ``torch-ao render --mesh`` on a generated closed mesh of about a
million triangles (a torus written as binary PLY) in fresh processes, and reports their peak RSS
against a process that only imports the same modules.

AO rays are realistic: cosine-distributed from the G-buffer points of each scene's default view.
Full references are timed with both AO-ray backends of ``render_reference`` on the CPU: ``torch``
(the tensor tracer) and ``kernel`` (the C++ pass of ``torch_ao.reference.ao_kernel``), at ``R = inf``
on the default layouts and at ``R = 1`` on layout 1 of the six scenes of ``torch-ao fit``.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from torch_ao.reference import Mesh, Plane, Scene, Tracer, embree_available, get_scene, icosphere, render_reference
from torch_ao.reference import sampling
from torch_ao.reference.render import default_views
from torch_ao.reference.warp_mesh import warp_available


def ao_rays(scene: Scene, n: int, device, seed: int = 0):
    """``n`` cosine-distributed rays from visible surface points of the scene's default view."""
    ref = render_reference(scene, default_views(scene, 90, 160), spp=2, uniform=False, progress=False, device=device)
    gb = ref.gbuffer
    M = ref.world_to_view[0].to(device, torch.float32)
    valid = gb.valid[0, 0]
    pv = ref.position[0][:, valid].T
    nv = gb.normals[0][:, valid].T
    p = (pv - M[:3, 3]) @ M[:3, :3]
    nw = nv @ M[:3, :3]
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(0, p.shape[0], (n,), generator=g).to(device)
    p, nw = p[pick], nw[pick]
    u1, u2 = torch.rand(n, generator=g).to(device), torch.rand(n, generator=g).to(device)
    t, b = sampling.frame(nw)
    loc = sampling.cosine_hemisphere(u1, u2)
    d = loc[:, :1] * t + loc[:, 1:2] * b + loc[:, 2:] * nw
    return p + 1e-4 * nw, d


def rays_per_second(fn, n: int, repeat: int = 3, device="cpu") -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        if device != "cpu":
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if device != "cpu":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return n / best


def torus_mesh(triangles: int, major: float = 1.0, minor: float = 0.3):
    """A closed torus (axis +Y, resting on y = 0) of about ``triangles`` triangles: numpy ``(V,3), (F,3)``."""
    import numpy as np

    nv = max(3, int(round(math.sqrt(triangles / 4))))
    nu = max(3, int(round(triangles / (2 * nv))))
    u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv, indexing="ij")
    ring = major + minor * np.cos(v)
    verts = np.stack([ring * np.cos(u), minor * np.sin(v) + minor, ring * np.sin(u)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def _child(argv: list[str]) -> tuple[float, float, int]:
    """Run ``python argv`` with this checkout's torch_ao: ``(seconds, peak RSS in MiB, exit status)``."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable] + argv, env=env, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - t, usage.ru_maxrss / 1024, proc.returncode  # ru_maxrss is in KiB on Linux


def large_mesh(triangles: int) -> None:
    import trimesh

    with tempfile.TemporaryDirectory() as tmp:
        verts, faces = torus_mesh(triangles)
        path = Path(tmp) / "torus.ply"
        trimesh.Trimesh(verts, faces, process=False).export(path)
        print(f"# {faces.shape[0]} triangles, {verts.shape[0]} vertices, {path.stat().st_size / 2**20:.0f} MiB PLY")
        _, base, _ = _child(["-c", "import torch_ao.reference, torch_ao.commands.render, trimesh, embreex.rtcore_scene"])
        print(f"imports only: peak RSS {base:.0f} MiB")
        print("| render | time s | peak RSS MiB | over imports MiB |")
        print("|---|---|---|---|")
        for size, spp, extra in (("320x180", 16, ["--backface"]), ("640x360", 64, [])):
            w, h = size.split("x")
            dt, rss, code = _child(["-m", "torch_ao.cli", "render", "--mesh", str(path), "--ground-plane", "--no-progress",
                                    "--width", w, "--height", h, "--spp", str(spp), "--max-distance", "0.3",
                                    "--no-uniform", "--out", str(Path(tmp) / "out.npz")] + extra)
            if code != 0:
                raise SystemExit(f"render failed with exit status {code}")
            print(f"| {size}, {spp} spp cosine AO{' + backface' if extra else ''} | {dt:.1f} | {rss:.0f} | {rss - base:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a smoke run)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--large", type=int, nargs="?", const=1_000_000, metavar="TRIANGLES",
                    help="only time torch-ao render on a generated mesh of this many triangles (default 1M), peak RSS")
    ap.add_argument("--references", action="store_true", help="only the full references (both backends)")
    args = ap.parse_args()
    if args.large:
        large_mesh(args.large)
        return
    dev = args.device
    n = 1 << (16 if args.quick else 20)
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.processor() or platform.machine()}, device {dev}")
    if not args.references:
        tracer_rays(dev, n)
    references(dev, args.quick)


def tracer_rays(dev, n: int) -> None:
    print("\n## torch tracer, analytic scenes (rays/s, chunks of", n, "rays)")
    print(f"| scene | primitives | AO rays R=inf (any hit) | AO rays R=1 | closest hit + normal |")
    print("|---|---|---|---|---|")
    for name in ("sphere_on_plane", "room_corner", "stairs", "fence", "poles"):
        scene = get_scene(name)
        tr = Tracer(scene, device=dev)
        o, d = ao_rays(scene, n, dev)
        r_inf = rays_per_second(lambda: tr.occluded(o, d, float("inf")), n, device=dev)
        r_1 = rays_per_second(lambda: tr.occluded(o, d, 1.0), n, device=dev)
        r_c = rays_per_second(lambda: tr.intersect(o, d), n, device=dev)
        print(f"| {name} | {len(scene.objects)} | {r_inf / 1e6:.1f} M | {r_1 / 1e6:.1f} M | {r_c / 1e6:.1f} M |")

    print("\n## meshes (rays/s, AO rays R=inf)")
    print("| mesh scene | triangles | backend | rays/s |")
    print("|---|---|---|---|")
    for sub in (1, 5):
        v, f = icosphere(sub, 0.5, (0.0, 0.5, 0.0))
        scene = Scene([Plane(), Mesh(vertices=v, faces=f)], view=get_scene("sphere_on_plane").view)
        backends = (["embree"] if embree_available() else []) + (["warp"] if warp_available() else []) \
            + (["torch"] if f.shape[0] <= 2000 else [])
        o, d = ao_rays(scene, n, dev)
        for backend in backends:
            tr = Tracer(scene, device=dev, mesh_backend=backend)
            mesh_group = tr.groups[-1]
            r = rays_per_second(lambda: mesh_group.occluded(o, d, float("inf")), n, device=dev)
            print(f"| icosphere on plane (mesh part only) | {f.shape[0]} | {backend} | {r / 1e6:.2f} M |")
            r = rays_per_second(lambda: tr.occluded(o, d, float("inf")), n, device=dev)
            print(f"| icosphere on plane (whole scene) | {f.shape[0]} | {backend} + torch plane | {r / 1e6:.2f} M |")



def references(dev, quick: bool) -> None:
    print("\n## full references (seconds; CPU = process time of all threads)")
    print("| scene | size | spp | R | what | AO rays | time | CPU | rays/s |")
    print("|---|---|---|---|---|---|---|---|---|")
    H, W, spp = (90, 160, 256) if quick else (180, 320, 1024)
    cases = [("sphere_on_plane", False, False, math.inf), ("sphere_on_plane", True, False, math.inf),
             ("stairs", False, False, math.inf), ("sphere_on_plane", False, True, math.inf)]
    cases += [(name, False, False, 1.0) for name in ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")]
    for name, uniform, indirect, R in cases:
        scene = get_scene(name, None if math.isinf(R) else 1)
        for backend in (("torch", "kernel") if dev == "cpu" and not indirect else ("torch",)):
            t, c = time.perf_counter(), time.process_time()
            ref = render_reference(scene, height=H, width=W, spp=spp, max_distance=R, uniform=uniform,
                                   indirect=indirect, progress=False, device=dev, backend=backend)
            dt, dc = time.perf_counter() - t, time.process_time() - c
            px = int(ref.gbuffer.valid.sum())
            rays = H * W + px * (1 + spp * (2 if uniform else 1) + (spp if indirect else 0))
            what = "cosine AO" + (" + uniform AO" if uniform else "") + (" + indirect" if indirect else "")
            print(f"| {name} | {W}x{H} | {spp} | {R:g} | {what} | {backend} | {dt:.2f} s | {dc:.2f} s | "
                  f"{rays / dt / 1e6:.1f} M |", flush=True)


if __name__ == "__main__":
    main()

"""Ray-tracer speed: rays per second (torch on analytic scenes, Embree and torch on meshes) and the
time of full references. Run: ``python benchmarks/bench_tracer.py [--quick] [--device cuda]``.

AO rays are realistic: cosine-distributed from the G-buffer points of each scene's default view.
"""
from __future__ import annotations

import argparse
import platform
import time

import torch

from torch_ao.reference import Mesh, Plane, Scene, Tracer, embree_available, get_scene, icosphere, render_reference
from torch_ao.reference import sampling
from torch_ao.reference.render import default_views


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


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a smoke run)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    dev = args.device
    n = 1 << (16 if args.quick else 20)
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.processor() or platform.machine()}, device {dev}")
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
        backends = (["embree"] if embree_available() else []) + (["torch"] if f.shape[0] <= 2000 else [])
        o, d = ao_rays(scene, n, dev)
        for backend in backends:
            tr = Tracer(scene, device=dev, mesh_backend=backend)
            mesh_group = tr.groups[-1]
            r = rays_per_second(lambda: mesh_group.occluded(o, d, float("inf")), n, device=dev)
            print(f"| icosphere on plane (mesh part only) | {f.shape[0]} | {backend} | {r / 1e6:.2f} M |")
            r = rays_per_second(lambda: tr.occluded(o, d, float("inf")), n, device=dev)
            print(f"| icosphere on plane (whole scene) | {f.shape[0]} | {backend} + torch plane | {r / 1e6:.2f} M |")

    print("\n## full references (seconds)")
    print("| scene | size | spp | what | time | rays/s |")
    print("|---|---|---|---|---|---|")
    H, W, spp = (90, 160, 256) if args.quick else (180, 320, 1024)
    for name, uniform, indirect in (("sphere_on_plane", False, False), ("sphere_on_plane", True, False),
                                    ("stairs", False, False), ("sphere_on_plane", False, True)):
        scene = get_scene(name)
        t = time.perf_counter()
        ref = render_reference(scene, height=H, width=W, spp=spp, max_distance=float("inf"), uniform=uniform,
                               indirect=indirect, progress=False, device=dev)
        dt = time.perf_counter() - t
        px = int(ref.gbuffer.valid.sum())
        rays = H * W + px * (1 + spp * (2 if uniform else 1) + (spp if indirect else 0))
        what = "cosine AO" + (" + uniform AO" if uniform else "") + (" + indirect" if indirect else "")
        print(f"| {name} | {W}x{H} | {spp} | {what} | {dt:.1f} s | {rays / dt / 1e6:.1f} M |")


if __name__ == "__main__":
    main()

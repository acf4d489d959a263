"""Which ``BitmaskAO`` / ``SSILVB`` calls a fused kernel computes, and why the others run on the tensor path.

Every combination of variant (``default``, ``exact``, ``hdrp``, ``ssilvb_glsl``), mode (hard, soft,
straight-through), weighting, thickness model (a scalar, the back-face layer, a map, the linear model, the net),
with or without a thickness growth, fetch (nearest, bilinear, edge-aware), output (visibility, indirect light, bent
normals, a constant ambient colour) and gradient (none, the parameters', the G-buffer's) that the modules accept is
asked of the dispatch
(``torch_ao.kernels.dispatch.KERNELS``: each kernel's ``covers``) on a small frame; nothing is run. Prints the count
of covered calls and the reasons for the others, most frequent first. Then the options beyond that table, one at a
time on the ``default`` and ``exact`` variants in each mode and with each gradient (the union, the ``exact``
variant's segment geometry, the projected normal's slices, a position buffer read bilinearly or edge-aware): how
many of those calls a kernel takes, and why not the others:

    python benchmarks/kernel_coverage.py
"""
from __future__ import annotations

import collections
import itertools
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's torch_ao, not an installed copy

import torch_ao  # noqa: E402
from torch_ao.examples import example_gbuffer  # noqa: E402
from torch_ao.kernels.dispatch import KERNELS  # noqa: E402
from torch_ao.thickness import BackfaceThickness, LinearThickness, MapThickness  # noqa: E402
from torch_ao.thickness_net import NetThickness  # noqa: E402

VARIANTS = ("default", "exact", "hdrp", "ssilvb_glsl")
MODES = ("hard", "soft", "straight_through")
WEIGHTINGS = ("uniform", "cosine")
FETCHES = ("nearest", "bilinear", "edge_aware")
OUTPUTS = ("visibility", "indirect", "bent normals", "ambient colour")
GRADIENTS = ("none", "parameters", "gbuffer")
GROWTHS = (None, 0.5)  # thickness_growth


def thickness_model(name: str, shape: tuple[int, ...]):
    """A fresh model (a model takes its module's growth: one per module)."""
    return {"scalar": lambda: 0.5, "backface": lambda: BackfaceThickness(0.8, 0.15),
            "map": lambda: MapThickness(torch.full(shape, 0.4)), "linear": lambda: LinearThickness(0.1, 0.2),
            "net": lambda: NetThickness(scale=1.0, init=0.3)}[name]()


def module_for(variant, mode, weighting, thickness, growth, fetch, output, gradient, shape):
    """The module of one combination, or ``None`` where the module refuses it (its own rule, not a kernel's)."""
    options = dict(variant=variant, mode=mode, weighting=weighting, fetch=fetch, slices=2, steps=2,
                   thickness=thickness_model(thickness, shape), thickness_growth=growth, trainable=gradient != "none")
    if output == "bent normals":
        options["bent_normals"] = True
    if output == "ambient colour":
        options["ambient"] = (0.1, 0.2, 0.3)
    try:
        return (torch_ao.SSILVB if output == "indirect" else torch_ao.BitmaskAO)(**options)
    except ValueError:
        return None


def uncovered(module, gbuffer) -> str | None:
    """Why no kernel of ``module`` computes its call on ``gbuffer`` (each kernel's reason), or ``None``."""
    reasons = []
    for covers, _ in KERNELS[module.has_kernel]:
        reason = covers(module, gbuffer)
        if reason is None:
            return None
        reasons.append(reason)
    return " / ".join(dict.fromkeys(reasons))


def main() -> int:
    plain = example_gbuffer(16, 24)
    plain = torch_ao.GBuffer(depth=plain.depth, camera=plain.camera, normals=plain.normals, light=plain.light,
                             backface_depth=plain.depth + 0.3)
    graph = torch_ao.GBuffer(depth=plain.depth.clone().requires_grad_(), camera=plain.camera,
                             normals=plain.normals.clone().requires_grad_(), light=plain.light,
                             backface_depth=plain.backface_depth)
    total, refused, reasons = 0, 0, collections.Counter()
    for combination in itertools.product(VARIANTS, MODES, WEIGHTINGS, ("scalar", "backface", "map", "linear", "net"),
                                         GROWTHS, FETCHES, OUTPUTS, GRADIENTS):
        module = module_for(*combination, shape=tuple(plain.depth.shape))
        if module is None:
            refused += 1
            continue
        total += 1
        reason = uncovered(module, graph if combination[-1] == "gbuffer" else plain)
        if reason is not None:
            reasons[reason] += 1
    print(f"{total} calls the modules accept ({refused} combinations they refuse): {total - sum(reasons.values())} "
          f"covered by a kernel, {sum(reasons.values())} on the tensor path")
    for reason, count in reasons.most_common():
        print(f"{count:6d}  {reason}")
    beyond(plain, graph)
    return 0


#: options beyond main()'s table, each alone: (label, module options, whether the G-buffer has a position buffer)
BEYOND = (("union='sectors'", dict(union="sectors"), False), ("union='exact'", dict(union="exact"), False),
          ("clip_to_radius=True", dict(clip_to_radius=True, union="sectors"), False),
          ("thickness_direction='depth'", dict(thickness_direction="depth", union="sectors"), False),
          ("sample_extent='sphere'", dict(sample_extent="sphere", union="sectors"), False),
          ("slice_sampling='projected_normal'", dict(slice_sampling="projected_normal"), False),
          ("position buffer, fetch='bilinear'", dict(fetch="bilinear"), True),
          ("position buffer, fetch='edge_aware'", dict(fetch="edge_aware"), True))


def beyond(plain, graph) -> None:
    """The options of :data:`BEYOND` on the default and exact variants, every mode and gradient."""
    print("\noptions beyond the table (default and exact variants, every mode and gradient):")
    print("| option | calls | covered | why not (the last kernel tried, most frequent) |")
    print("|---|---:|---:|---|")
    for label, extra, position in BEYOND:
        count, covered, reasons = 0, 0, collections.Counter()
        for variant, mode, gradient in itertools.product(("default", "exact"), MODES, GRADIENTS):
            try:
                module = torch_ao.BitmaskAO(variant=variant, mode=mode, slices=2, steps=2, trainable=gradient != "none",
                                            **extra)
            except ValueError:
                continue
            gb = graph if gradient == "gbuffer" else plain
            if position:
                gb = torch_ao.GBuffer(depth=None, camera=gb.camera, normals=gb.normals, light=gb.light,
                                      position=gb.positions().detach().clone().requires_grad_(gradient == "gbuffer"))
            count += 1
            reason = uncovered(module, gb)
            if reason is None:
                covered += 1
            else:
                reasons[reason.split(" / ")[-1]] += 1  # (the last kernel tried: the soft one)
        why = reasons.most_common(1)[0][0] if reasons else ""
        print(f"| {label} | {count} | {covered} | {why} |")


if __name__ == "__main__":
    raise SystemExit(main())

"""``torch-ao ao --auto``: the bench recommendation applied to the parsed command line."""
from __future__ import annotations

import argparse
from typing import Callable

from ..bench import auto_choice

__all__ = ["apply_auto"]


def apply_auto(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    """Set ``args.method``/``args.preset`` (and ``args.radius`` when not given) from
    :func:`~torch_ao.bench.auto_choice` on ``args.gbuffer``, ``args.report`` and ``args.tolerance``."""
    if not getattr(args, "auto", False):
        raise ValueError("--report/--tolerance: only meaningful with --auto")
    if args.report is None and args.gbuffer:
        log(f"auto: no --report; running a quick sweep on {args.gbuffer}'s reference (all methods, low..ultra)")
    choice = auto_choice(args.gbuffer, report=args.report, tolerance=args.tolerance, device=args.device,
                         progress=getattr(args, "progress", True), log=None)
    args.method, args.preset = choice["method"], choice["preset"]
    if getattr(args, "radius", None) is None and choice["radius"] is not None:
        args.radius = choice["radius"]
    b = choice["best"]
    log(f"auto: {choice['method']} preset {choice['preset']} (MAE {choice['mae']:.4f}, {choice['forward_ms']:.1f} ms; "
        f"best {b['method']} {b['preset']} MAE {b['mae']:.4f}; tolerance {choice['tolerance']:g}) from {choice['source']}")
    return choice

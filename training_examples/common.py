"""Pieces the fitting examples share: smoke-test settings and their reference views.

The scripts import this file from their own folder (``python training_examples/NAME.py`` puts that
folder on the import path); copy it along when you copy a script.
"""
from __future__ import annotations

import argparse

import torch

from torch_ao.datasets import train_and_holdout_views
from torch_ao.fit import FitView, load_views
from torch_ao.fitted import FittedPipeline


def apply_tiny(parser: argparse.ArgumentParser, args: argparse.Namespace, **settings) -> argparse.Namespace:
    """With ``--tiny``, replace the options the user left at their defaults by ``settings``."""
    if args.tiny:
        for key, value in settings.items():
            if getattr(args, key) == parser.get_default(key):  # options the user changed are kept
                setattr(args, key, value)
    return args


def add_view_options(parser: argparse.ArgumentParser, *, size: str, spp: int = 128, max_distance: float = 1.0,
                     radius_note: str = " (also the method's radius)", holdout_note: str = "per scene") -> None:
    """The options every script's views share: ``--holdout-views``, ``--size``, ``--spp``, ``--max-distance``
    (world units) and ``--cache``, with the script's defaults."""
    parser.add_argument("--holdout-views", type=int, default=1, help=f"held-out views {holdout_note}")
    parser.add_argument("--size", default=size, help="render size WxH")
    parser.add_argument("--spp", type=int, default=spp, help="reference rays per pixel")
    parser.add_argument("--max-distance", type=float, default=max_distance, help="reference AO distance R" + radius_note)
    parser.add_argument("--cache", default=None, help="reference cache folder (default $TORCH_AO_CACHE or ~/.cache/torch_ao)")


def bitmask(args: argparse.Namespace, thickness) -> FittedPipeline:
    """The shipped pipeline the bitmask thickness fits tune: bitmask AO (hard mode) followed by the denoiser (unless
    ``--no-denoise``), with ``add_bitmask_fit_options``' sampling and this ``thickness`` (a number, or a model's
    value such as a per-object table)."""
    options = dict(preset=args.preset, radius=args.max_distance, weighting=args.weighting, thickness=thickness)
    return FittedPipeline("bitmask", options, denoiser=not args.no_denoise).to(args.device)


def add_bitmask_fit_options(parser: argparse.ArgumentParser, *, init_help: str, steps_help: str) -> None:
    """The options both bitmask thickness fits share: sampling (``--preset``, ``--weighting``), the
    optimizer (``--init``, ``--steps``, ``--lr``, ``--batch-views``), the denoiser and the hard-mode
    scoring."""
    parser.add_argument("--preset", default="medium", help="quality preset (slices x steps per side)")
    parser.add_argument("--weighting", default="cosine", choices=("uniform", "cosine"), help="bitmask sector weighting")
    parser.add_argument("--init", type=float, default=1.0, help=init_help)
    parser.add_argument("--steps", type=int, default=30, help=steps_help)
    parser.add_argument("--lr", type=float, default=0.05)
    parser.add_argument("--batch-views", type=int, default=0,
                        help="views per step (0 = all: the best step is then chosen on the whole set)")


def add_run_options(parser: argparse.ArgumentParser, *, out: str, hard_every: bool = True) -> None:
    """The options every fitting script's run shares: the denoiser, hard-mode scoring, the seed, the output
    folder, the device and the progress bar."""
    parser.add_argument("--no-denoise", action="store_true", help="fit and score the method alone, without the denoiser")
    if hard_every:
        parser.add_argument("--hard-every", type=int, default=5,
                            help="score in hard mode every N steps and keep the best (0 = off)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=out, help="output folder")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--no-progress", action="store_true")


def build_views(args: argparse.Namespace) -> tuple[list[FitView], list[FitView]]:
    """Training and held-out views: the user's ``--reference``/``--holdout`` files, else randomised
    views of the built-in ``--scenes`` (seeds 1.. for training, 1000.. held out), cached."""
    device = torch.device(args.device)
    if args.reference:
        train = load_views(args.reference, device=device)
        held = load_views(args.holdout, device=device) if args.holdout else train
        return train, held
    w, h = (int(x) for x in args.size.lower().split("x"))
    scenes = [s for s in args.scenes.split(",") if s]
    return train_and_holdout_views(scenes, args.train_views, args.holdout_views, height=h, width=w, spp=args.spp,
                                   max_distance=args.max_distance, cache_dir=args.cache, device=device,
                                   progress=not args.no_progress)

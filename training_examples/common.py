"""Pieces the fitting examples share: smoke-test settings and their reference views.

The scripts import this file from their own folder (``python training_examples/NAME.py`` puts that
folder on the import path); copy it along when you copy a script.
"""
from __future__ import annotations

import argparse

import torch

from torch_ao.datasets import train_and_holdout_views
from torch_ao.fit import FitView, load_views


def apply_tiny(parser: argparse.ArgumentParser, args: argparse.Namespace, **settings) -> argparse.Namespace:
    """With ``--tiny``, replace the options the user left at their defaults by ``settings``."""
    if args.tiny:
        for key, value in settings.items():
            if getattr(args, key) == parser.get_default(key):  # options the user changed are kept
                setattr(args, key, value)
    return args


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

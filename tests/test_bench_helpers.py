"""Helpers of the bench tests (no tests here): a tiny horizon method on the shared core, so the bench and
opt-in tests do not depend on which methods have landed (the real ones are exercised too, where importable)."""
import torch

from torch_ao.methods import METHODS, get_method
from torch_ao.methods.base import ScreenSpaceAO
from torch_ao.walk import SliceAccumulator


class _MaxHorizon(SliceAccumulator):
    def begin_slice(self, q, geom):
        return torch.full_like(q.depth, -1.0)

    def step(self, state, q, geom, sample):
        c = torch.where(sample.valid & (sample.distance < 1.0), sample.cos_view(), -torch.ones_like(state))
        return torch.maximum(state, c)

    def end_slice(self, state, q, geom):
        return {"visibility": (1 - state.clamp(0, 1))[:, None]}

    def finish(self, sums, q, n):
        return {"visibility": sums["visibility"] / n}


class TinyAO(ScreenSpaceAO):
    """1 - mean over slices of the largest horizon cosine within radius 1 (a crude SSAO)."""

    def accumulator(self, frame):
        return _MaxHorizon()


def importable_methods():
    """Every registry method (an import error is a failure, not a skip)."""
    return {name: get_method(name) for name in METHODS}

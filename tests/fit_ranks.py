"""A tiny fit run by ``tests/test_fit_distributed.py`` in one process (``python tests/fit_ranks.py``) and
under ``torchrun --nproc_per_node 2``: a two-parameter toy module on five views read from files, with
partial batches, hard-mode scores and checkpoints. Each rank writes ``OUT/rank<r>.json`` (its result and
how many files it read); ``--crash-after N`` makes rank 1 (rank 0 of one process) fail at its N-th forward,
leaving a checkpoint to resume from."""
import argparse
import json
import os
import sys

import torch
from torch import nn

from torch_ao import distributed
from torch_ao.examples import plane_gbuffer
from torch_ao.fit import FitConfig, fit
from torch_ao.fit_data import ViewFiles
from torch_ao.io import save_npz
from torch_ao.methods.base import AOOutput

CONFIG = FitConfig(params=("thickness", "offset"), steps=9, lr=0.05, loss="mse", batch_views=3, hard_every=3,
                   checkpoint_every=3, seed=7)


class Toy(nn.Module):
    """visibility = exp(-thickness (depth - 3)^2 / 4) + offset: smooth in both parameters."""

    def __init__(self, thickness=1.5, offset=0.0, crash_after=0):
        super().__init__()
        self.thickness = nn.Parameter(torch.tensor(float(thickness)))
        self.offset = nn.Parameter(torch.tensor(float(offset)))
        self.mode, self.tau = "hard", 0.1
        self.calls, self.crash_after = 0, crash_after

    def forward(self, gb):
        self.calls += 1
        if self.crash_after and self.calls >= self.crash_after:
            raise RuntimeError(f"crash at forward {self.calls}")
        return AOOutput(torch.exp(-self.thickness * (gb.safe_depth - 3).square() / 4) + self.offset)


def write_views(folder, n=5):
    """``n`` tilted planes with references of thickness 0.3, offset 0.05; returns their paths."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    for i in range(n):
        gb = plane_gbuffer(12, 16, tilt_degrees=30 + 7 * i)
        with torch.no_grad():
            ref = Toy(0.3, 0.05)(gb).visibility
        paths.append(save_npz(os.path.join(folder, f"v{i}.npz"), gb, ao=ref))
    return paths


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("views")
    p.add_argument("out")
    p.add_argument("--crash-after", type=int, default=0)
    args = p.parse_args()
    distributed.init_from_environment("cpu")
    rank = distributed.rank()
    crash = args.crash_after if rank == distributed.world_size() - 1 else 0
    views = ViewFiles(sorted(os.path.join(args.views, f) for f in os.listdir(args.views)), cache_size=0)
    module = Toy(crash_after=crash)
    result = fit(module, views, CONFIG, checkpoint=os.path.join(args.out, "checkpoint.pt"), progress=False)
    with open(os.path.join(args.out, f"rank{rank}.json"), "w") as f:
        json.dump({"world": distributed.world_size(), "parameters": result.parameters,
                   "history": [r["loss"] for r in result.history], "hard": [r["loss"] for r in result.hard_history],
                   "best_step": result.best_step, "reads": views.reads}, f)
    distributed.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())

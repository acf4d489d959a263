"""Train a small CNN that predicts a per-pixel bitmask-AO thickness map from G-buffer features.

What it does
    One thickness for a whole frame is a compromise between thin occluders (slats, poles) and thick
    ones (walls, boxes). :class:`~torch_ao.methods.bitmask.BitmaskAO` also accepts a ``(B,1,H,W)``
    thickness *map* (read at each sample, i.e. the occluder's thickness). This script trains
    :class:`ThicknessNet` -- about 6k weights, scale-free inputs: relative log-depth, normals,
    log-depth gradients, the pixel footprint and the valid mask -- to produce that map, so that
    the *soft* bitmask AO of the frame matches the ray-traced reference (L1 on valid pixels).

    * Data: randomised built-in scenes; every epoch uses new random seeds (``--seed-pool`` of them
      per scene, rendered once and then read from the cache).
    * Evaluation: held-out views (seeds >= 1000, never trained on) in *hard* mode, against the best
      scalar thickness (a grid search on the training views, or ``--scalar``).
    * Nothing lost: an atomic checkpoint (model, optimizer, step, every rank's RNG state) every
      ``--checkpoint-every`` steps; the same command resumes where it stopped and ends with the same
      weights as an uninterrupted run.
    * Distributed: under ``torchrun`` it runs DistributedDataParallel (``gloo`` on CPU, ``nccl`` on
      CUDA, one GPU per process). Each rank renders and trains on its own shard of every epoch's
      views; gradients are averaged, so every rank holds the same weights. Only rank 0 prints,
      evaluates and writes results; every rank writes ``OUT/rank<r>.json`` (world size, views seen,
      a checksum of its final weights).

How to run
    python training_examples/train_thickness_net.py                # about 3 minutes of CPU time on 2 cores
    torchrun --standalone --nproc_per_node=2 training_examples/train_thickness_net.py
    python training_examples/train_thickness_net.py --tiny          # a smoke test (under a minute)
    Outputs in ``--out``: ``thickness_net.pt`` (state dict, load with ``weights_only=True``),
    ``result.json`` (held-out metrics), ``checkpoint.pt``.

How to adapt
    * More data / bigger images: ``--seed-pool 50 --epochs 20 --size 160x96 --spp 256``, or your own
      frames: replace :func:`epoch_views` by a list of :class:`torch_ao.fit.FitView` (``load_views``).
    * Other features or a bigger network: edit :func:`features` / :class:`ThicknessNet` (the
      output must stay positive: ``softplus``).
    * Use the trained net::

          net = ThicknessNet(); net.load_state_dict(torch.load("thickness_net.pt", weights_only=True))
          ao = BitmaskAO(preset="medium", radius=R, thickness=torch.ones(1, 1, H, W), trainable=False)
          ao.thickness = net(features(gbuffer, R))          # (B,1,H,W) map, set per frame
          visibility = ao(gbuffer).visibility
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import random
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn

from torch_ao import GBuffer
from torch_ao.datasets import TRAIN_SCENES, reference_view
from torch_ao.fit import FitView, remove_stale_temporaries, rng_state, save_checkpoint, set_rng_state
from torch_ao.io import save_json
from torch_ao.methods import get_method
from torch_ao.metrics import error_metrics

from common import apply_tiny


# ---------------------------------------------------------------------------------------------
# Model
# ---------------------------------------------------------------------------------------------
IN_CHANNELS = 8


def features(gbuffer: GBuffer, radius: float) -> torch.Tensor:
    """``(B, 8, H, W)`` scale-free inputs; background pixels are 0.

    Channels: ``log(depth / median depth)``, view normals (3), ``d log depth / dx`` and ``/ dy``
    (depth discontinuities), ``log(pixel footprint / radius)`` (how many pixels the radius spans),
    the valid mask.
    """
    valid = gbuffer.valid
    depth = gbuffer.safe_depth
    vf = valid.to(depth.dtype)
    log_d = torch.log(depth)
    B = depth.shape[0]
    med = torch.stack([log_d[b][valid[b]].median() if bool(valid[b].any()) else log_d.new_zeros(()) for b in range(B)])
    rel = (log_d - med.view(B, 1, 1, 1)) * vf
    normals = gbuffer.view_normals() * vf
    gx = F.pad(log_d[..., :, 1:] - log_d[..., :, :-1], (0, 1)) * vf * F.pad(vf[..., :, 1:], (0, 1))
    gy = F.pad(log_d[..., 1:, :] - log_d[..., :-1, :], (0, 0, 0, 1)) * vf * F.pad(vf[..., 1:, :], (0, 0, 0, 1))
    fy = gbuffer.camera.intrinsics[:, 1, 1].to(depth.dtype).view(-1, 1, 1, 1)
    footprint = torch.log(depth / fy / radius) * vf
    x = torch.cat([rel, normals, gx.clamp(-1, 1), gy.clamp(-1, 1), footprint, vf], 1)
    return x.float()


class ThicknessNet(nn.Module):
    """Features -> positive thickness map in world units: ``radius * softplus(conv(x))``.

    Four 3x3 convolutions with dilations 1, 2, 4, 1 (receptive field 17 pixels); the output starts
    at ``init`` everywhere (last layer's weights zero, bias ``softplus^-1(init / radius)``).
    """

    def __init__(self, width: int = 16, init: float = 0.5, radius: float = 1.0) -> None:
        super().__init__()
        self.radius = float(radius)
        layers, c = [], IN_CHANNELS
        for d in (1, 2, 4):
            layers += [nn.Conv2d(c, width, 3, padding=d, dilation=d), nn.ReLU()]
            c = width
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(width, 1, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        r = init / self.radius
        nn.init.constant_(self.head.bias, r + math.log(-math.expm1(-r)))  # softplus^-1(r)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.radius * F.softplus(self.head(self.body(x)))


# ---------------------------------------------------------------------------------------------
# Data: every epoch new seeds; each rank takes its shard
# ---------------------------------------------------------------------------------------------
def render(args, scene: str, seed: int, device) -> FitView:
    w, h = (int(x) for x in args.size.lower().split("x"))
    return reference_view(scene, seed, height=h, width=w, spp=args.spp, max_distance=args.max_distance,
                          cache_dir=args.cache, device=device)


def epoch_views(args, epoch: int) -> list[tuple[str, int]]:
    """The (scene, seed) pairs of ``epoch``, shuffled (same list on every rank)."""
    scenes = [s for s in args.scenes.split(",") if s]
    g = torch.Generator().manual_seed(args.seed * 7919 + epoch)
    pairs = []
    for scene in scenes:
        first = epoch * args.views_per_scene
        pairs += [(scene, 1 + (first + i) % args.seed_pool) for i in range(args.views_per_scene)]
    return [pairs[i] for i in torch.randperm(len(pairs), generator=g).tolist()]


def shard(items: list, steps: int, batch: int, rank: int, world: int) -> list[list]:
    """``steps`` batches of ``batch`` items for ``rank`` (items padded by wrapping around, so that
    every rank runs the same number of steps -- DDP needs that)."""
    need = steps * batch * world
    padded = [items[i % len(items)] for i in range(need)]
    mine = padded[rank::world]
    return [mine[i * batch:(i + 1) * batch] for i in range(steps)]


# ---------------------------------------------------------------------------------------------
# Distributed set-up and checkpoints
# ---------------------------------------------------------------------------------------------
def setup_distributed():
    """(rank, world size, device); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if torch.cuda.is_available():
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    if world > 1:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return rank, world, device


def weights_checksum(model: nn.Module) -> str:
    h = hashlib.sha256()
    for name, p in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(p.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------
# Training and evaluation
# ---------------------------------------------------------------------------------------------
def batch_loss(ao: nn.Module, net: nn.Module, views: list[FitView], radius: float) -> torch.Tensor:
    """Mean over ``views`` of the L1 error on valid pixels of soft bitmask AO with the net's thickness maps.

    The net runs once on the stacked features of all views (DDP wants one forward per backward);
    the AO module then runs per view with that view's map set as its ``thickness``.
    """
    x = torch.cat([features(v.gbuffer, radius) for v in views])
    maps = net(x).split([v.gbuffer.depth.shape[0] for v in views])
    losses = []
    for view, t in zip(views, maps):
        ao.thickness = t.to(view.gbuffer.depth.dtype)
        vis = ao(view.gbuffer).visibility
        losses.append((vis - view.reference)[view.gbuffer.valid].abs().mean())
    return torch.stack(losses).mean()


@torch.no_grad()
def evaluate_map(ao: nn.Module, views: list[FitView], thickness) -> dict:
    """Mean hard-mode metrics; ``thickness`` is a float or a callable ``view -> (B,1,H,W) map``."""
    ao.mode = "hard"
    rows = []
    for v in views:
        t = thickness(v) if callable(thickness) else torch.full_like(v.gbuffer.depth, float(thickness))
        ao.thickness = t.to(v.gbuffer.depth.dtype)
        rows.append(error_metrics(ao(v.gbuffer).visibility, v.reference, v.gbuffer.valid))
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes to train and evaluate on")
    p.add_argument("--views-per-scene", type=int, default=2, help="training views per scene and epoch")
    p.add_argument("--seed-pool", type=int, default=8, help="distinct random seeds per scene (epochs cycle through them)")
    p.add_argument("--holdout-views", type=int, default=1, help="held-out views per scene (seeds 1000, 1001, ...)")
    p.add_argument("--size", default="64x48", help="render size WxH")
    p.add_argument("--spp", type=int, default=128, help="reference rays per pixel")
    p.add_argument("--max-distance", type=float, default=1.0, help="reference AO distance R (also the method's radius)")
    p.add_argument("--preset", default="medium", help="bitmask quality preset")
    p.add_argument("--weighting", default="cosine", choices=("uniform", "cosine"))
    p.add_argument("--epochs", type=int, default=8)
    p.add_argument("--batch", type=int, default=2, help="views per step and rank")
    p.add_argument("--lr", type=float, default=5e-3)
    p.add_argument("--width", type=int, default=16, help="channels of the CNN")
    p.add_argument("--init", type=float, default=0.5, help="thickness the untrained net outputs everywhere")
    p.add_argument("--tau", default="0.5,0.1", help="soft temperature schedule start,end (sector units, geometric)")
    p.add_argument("--scalar", type=float, default=None, help="scalar thickness to compare with (default: grid search)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=2, help="steps between checkpoints")
    p.add_argument("--cache", default=None, help="reference cache folder (default $TORCH_AO_CACHE or ~/.cache/torch_ao)")
    p.add_argument("--out", default="runs/thickness_net", help="output folder")
    p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (for tests of resuming)")
    p.add_argument("--no-eval", action="store_true", help="skip the held-out evaluation")
    p.add_argument("--tiny", action="store_true", help="smoke test (options left at their defaults are replaced): 2 scenes, 32x24, 16 spp, low preset, 2 epochs")
    return apply_tiny(p, p.parse_args(argv), scenes="fence,floating", size="32x24", spp=16, preset="low",
                      views_per_scene=2, seed_pool=2, epochs=2, batch=1)


def main(argv=None) -> dict | None:
    args = parse_args(argv)
    rank, world, device = setup_distributed()
    say = print if rank == 0 else (lambda *a, **k: None)
    out = Path(args.out)
    R = args.max_distance
    tau0, tau1 = (float(x) for x in args.tau.split(","))

    torch.manual_seed(args.seed)  # same initial weights on every rank (DDP also broadcasts rank 0's)
    np.random.seed(args.seed + rank)
    random.seed(args.seed + rank)
    net = ThicknessNet(args.width, args.init, R).to(device)
    model = nn.parallel.DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None) \
        if world > 1 else net
    optimizer = torch.optim.Adam(net.parameters(), lr=args.lr)
    ao = get_method("bitmask")(preset=args.preset, radius=R, weighting=args.weighting, mode="soft", tau=tau0,
                               thickness=torch.ones(1, 1, 1, 1), trainable=False).to(device)

    per_epoch = math.ceil(len(epoch_views(args, 0)) / (args.batch * world))
    total = per_epoch * args.epochs
    ckpt = out / "checkpoint.pt"
    fingerprint = {k: v for k, v in vars(args).items() if k not in ("out", "cache", "max_steps", "no_eval", "checkpoint_every", "scalar")}
    fingerprint["world_size"] = world
    step, history = 0, []
    if rank == 0:
        remove_stale_temporaries(ckpt)  # left by a run killed while writing its checkpoint
    if ckpt.exists():
        saved = torch.load(ckpt, map_location="cpu", weights_only=True)
        if saved["config"] != fingerprint:
            raise SystemExit(f"error: {ckpt} was written with other settings (or world size); remove it or use another --out")
        net.load_state_dict(saved["model"])
        optimizer.load_state_dict(saved["optimizer"])
        step, history = saved["step"], saved["history"]
        set_rng_state(saved["rng"][rank])
        say(f"resumed from {ckpt} at step {step}/{total}")
    say(f"training ThicknessNet ({sum(p.numel() for p in net.parameters())} weights) on {world} process(es), "
        f"{device.type}: {args.epochs} epochs x {per_epoch} steps x {args.batch} views/rank, {args.size}, preset {args.preset}")

    seen = []
    t_start = time.perf_counter()
    stop = total if args.max_steps is None else min(total, args.max_steps)
    while step < stop:
        epoch, k = divmod(step, per_epoch)
        batch = shard(epoch_views(args, epoch), per_epoch, args.batch, rank, world)[k]
        views = [render(args, s, seed, device) for s, seed in batch]
        ao.tau = math.exp(math.log(tau0) + (math.log(tau1) - math.log(tau0)) * step / max(1, total - 1))
        ao.mode = "soft"
        optimizer.zero_grad(set_to_none=True)
        loss = batch_loss(ao, model, views, R)
        loss.backward()  # DDP averages the gradients over ranks here
        optimizer.step()
        seen += [v.name for v in views]
        mean_loss = loss.detach().clone()
        if world > 1:
            dist.all_reduce(mean_loss)
            mean_loss /= world
        history.append({"step": step, "epoch": epoch, "loss": float(mean_loss), "tau": ao.tau})
        if step % max(1, total // 20) == 0 or step == total - 1:
            say(f"step {step + 1}/{total}  epoch {epoch}  loss {float(mean_loss):.4f}  tau {ao.tau:.3f}", flush=True)
        step += 1
        if step % args.checkpoint_every == 0 or step == stop:
            states = [None] * world
            if world > 1:
                dist.all_gather_object(states, rng_state())
            else:
                states = [rng_state()]
            if rank == 0:
                save_checkpoint(ckpt, {"config": fingerprint, "model": net.state_dict(), "optimizer": optimizer.state_dict(),
                                       "step": step, "history": history, "rng": states})
    seconds = time.perf_counter() - t_start

    checksum = weights_checksum(net)
    save_json(out / f"rank{rank}.json", {"rank": rank, "world_size": world, "steps": step, "views_seen": seen, "checksum": checksum,
                 "backend": dist.get_backend() if world > 1 else None})
    result = None
    if rank == 0 and step == total:
        save_checkpoint(out / "thickness_net.pt", net.state_dict())
        result = {"steps": step, "world_size": world, "train_seconds": seconds, "history": history, "checksum": checksum}
        if not args.no_eval:
            result.update(evaluate(args, net, ao, device))
        save_json(out / "result.json", result)
        say(f"wrote {out / 'thickness_net.pt'}, {out / 'result.json'}")
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return result


def evaluate(args, net: nn.Module, ao: nn.Module, device) -> dict:
    """Held-out hard-mode error of the net's maps and of the best scalar thickness."""
    R = args.max_distance
    scenes = [s for s in args.scenes.split(",") if s]
    held = [render(args, s, 1000 + i, device) for s in scenes for i in range(args.holdout_views)]
    net.eval()
    if args.scalar is not None:
        scalar, grid = args.scalar, {}
    else:  # the best single thickness on (the first epoch's) training views, hard mode
        train = [render(args, s, seed, device) for s, seed in epoch_views(args, 0)]
        grid = {t * R: evaluate_map(ao, train, t * R)["mae"] for t in (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 4.0)}
        scalar = min(grid, key=grid.get)
    with torch.no_grad():
        maps = [net(features(v.gbuffer, R)) for v in held]
    rows = {"untrained net (init everywhere)": evaluate_map(ao, held, args.init),
            f"best scalar ({scalar:g})": evaluate_map(ao, held, scalar),
            "thickness net": evaluate_map(ao, held, lambda v: net(features(v.gbuffer, R)))}
    print(f"\n{'held-out views, hard mode':<32}{'MAE':>8}{'RMSE':>8}{'PSNR':>8}{'SSIM':>8}")
    for name, r in rows.items():
        print(f"{name:<32}{r['mae']:8.4f}{r['rmse']:8.4f}{r['psnr']:8.2f}{r['ssim']:8.4f}")
    all_maps = torch.cat([m[v.gbuffer.valid] for m, v in zip(maps, held)])
    q = torch.quantile(all_maps.float().cpu(), torch.tensor([0.05, 0.5, 0.95])).tolist()
    print(f"predicted thickness on held-out valid pixels: 5% {q[0]:.3f}, median {q[1]:.3f}, 95% {q[2]:.3f}")
    return {"holdout": rows, "scalar": scalar, "scalar_grid_train_mae": {f"{k:g}": v for k, v in grid.items()},
            "holdout_thickness_quantiles": q, "holdout_views": [v.name for v in held]}


if __name__ == "__main__":
    main()

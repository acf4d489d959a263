"""Train the learned per-pixel thickness (:class:`torch_ao.thickness.NetThickness`) on back-face layers.

What it does
    One thickness for a whole frame is a compromise between thin occluders (slats, poles) and thick
    ones (walls, boxes); a back-face depth layer gives every occluder its own, but needs a second depth
    pass. :class:`~torch_ao.thickness.NetThickness` -- a CNN of about 6k weights on scale-free features
    of the front G-buffer alone (``torch_ao.thickness_net.net_features``: relative log-depth, normals,
    log-depth gradients, pixel footprint in units of R, valid mask) -- predicts that thickness. Two stages:

    a. *supervised*: L1 (in units of R) against the true back-face thickness ``backface_depth - depth``
       (the exit depth of each camera ray, ray-traced with ``backface=True``), capped at ``--cap`` x R
       (and ``--cap`` x R where the ray never leaves the object: planes, open meshes);
    b. *end-to-end* (``--finetune-epochs``, default 0): the soft bitmask L1 against the ray-traced AO.

    * Data: randomised built-in scenes (new seeds each epoch, ``--seed-pool`` of them per scene) and
      orbit views of real meshes (``--meshes``, Debian's assimp-testmodels, each normalised to unit
      size on a floor), rendered once with their back-face layer and cached.
    * Evaluation on held-out views -- seeds 1000, 1001... of the scenes and of ``--holdout-meshes``,
      meshes never trained on: the thickness MAE against the true (capped) back-face thickness, and the
      AO error of bitmask ``--eval-preset`` followed by the denoiser, hard mode, with (i) the best scalar
      thickness (a grid search on training views), (ii) the net, (iii) the true back-face layer
      (:class:`~torch_ao.thickness.BackfaceThickness`, the upper bound).
    * Nothing lost: an atomic checkpoint (model, optimizer, step, every rank's RNG state) every
      ``--checkpoint-every`` steps; the same command resumes where it stopped and ends with the same
      weights as an uninterrupted run.
    * Distributed: under ``torchrun`` it runs DistributedDataParallel (``gloo`` on CPU, ``nccl`` on
      CUDA, one GPU per process). Each rank renders and trains on its own shard of every epoch's
      views; gradients are averaged, so every rank holds the same weights. Only rank 0 prints,
      evaluates and writes results; every rank writes ``OUT/rank<r>.json`` (world size, views seen,
      a checksum of its final weights). The process group is torch_ao.distributed's; a rank leaves
      with ``os._exit`` once its files are written, since DDP keeps gloo's threads alive into the
      interpreter's shutdown, where they can abort a finished rank.

How to run
    nice -n 10 python training_examples/train_thickness_net.py     # a few minutes of CPU time
    python training_examples/train_thickness_net.py --finetune-epochs 2   # then end-to-end through BitmaskAO
    torchrun --standalone --nproc_per_node=2 training_examples/train_thickness_net.py
    python training_examples/train_thickness_net.py --tiny          # a smoke test (under a minute)
    Outputs in ``--out``: ``thickness_net.pt`` (``NetThickness.load`` reads it), ``result.json``
    (held-out metrics), ``checkpoint.pt``.

How to adapt
    * More data / bigger images: ``--seed-pool 50 --epochs 20 --size 160x96 --spp 256``, more
      ``--meshes``, or your own frames with a ``backface_depth`` layer: replace :func:`epoch_views`.
    * Other features or a bigger network: ``torch_ao.thickness_net`` (the output must stay positive).
    * Use the trained net::

          model = NetThickness.load("thickness_net.pt")
          ao = BitmaskAO(preset="high", radius=R, weighting="cosine", thickness=model)  # weights = parameters
          visibility = Denoiser()(ao(gbuffer).visibility, gbuffer).visibility
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import random
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from torch_ao import distributed as ranks
from torch_ao.datasets import TRAIN_SCENES
from torch_ao.fit import FitView, evaluate, load_views, remove_stale_temporaries, rng_state, save_checkpoint, set_rng_state
from torch_ao.fitted import DenoisedAO
from torch_ao.io import save_json
from torch_ao.methods import get_method
from torch_ao.thickness import BackfaceThickness, NetThickness
from torch_ao.thickness_net import ThicknessCNN, net_features
from torch_ao.views import default_cache_dir

from common import add_view_options, apply_tiny

MESH_DIR = Path("/usr/share/assimp/models")
#: training meshes (assimp-testmodels; spider, duck, engine and wuson are kept for independent checks)
TRAIN_MESHES = ("OBJ/empty_mat.obj", "STL/sphereWithHole.stl", "STL/3DSMaxExport.STL", "OBJ/box_longline.obj")
#: held-out meshes, never trained on
HOLDOUT_MESHES = ("OBJ/regr01.obj", "glTF2/ClearCoat-glTF/ClearCoatTest.gltf")
HOLDOUT_SEED = 1000
#: the net at the end of stage a, when stage b follows (``OUT/thickness_net_stage_a.pt``)
STAGE_A = "thickness_net_stage_a.pt"


# ---------------------------------------------------------------------------------------------
# Data: views with their back-face layer; every epoch new seeds; each rank takes its shard
# ---------------------------------------------------------------------------------------------
def _mesh_path(name: str) -> Path:
    path = Path(name)
    return path if path.is_absolute() or path.exists() else MESH_DIR / path


def _scene_and_views(source: str, seed: int, width: int, height: int):
    """``(scene, views)`` of a built-in scene (randomised layout ``seed``) or of a mesh file on a floor,
    normalised to unit size and seen from an orbit camera drawn from ``seed`` (azimuth uniform,
    elevation 15-50 degrees, far enough for its bounding sphere to fill most of the 60-degree view)."""
    from torch_ao.reference import get_scene, look_at, mesh_scene

    if not source.startswith("mesh:"):
        scene = get_scene(source, seed)
        v = scene.view
        return scene, look_at(v.eye, v.target, v.up, v.fov_y_degrees, height=height, width=width)
    path = _mesh_path(source[5:])
    if not path.exists():
        raise SystemExit(f"error: --meshes: {path} does not exist (apt-get install assimp-testmodels)")
    scene = mesh_scene([path], ground_plane=True, normalize=True)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in scene.bounds())
    centre, r = (lo + hi) / 2, float((hi - lo).norm()) / 2
    g = torch.Generator().manual_seed(seed)
    az, el = 2 * math.pi * float(torch.rand((), generator=g)), math.radians(15 + 35 * float(torch.rand((), generator=g)))
    d = (0.9 + 0.4 * float(torch.rand((), generator=g))) * r / math.sin(math.radians(30))
    eye = centre + d * torch.tensor([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)], dtype=torch.float64)
    return scene, look_at(eye.tolist(), centre.tolist(), (0.0, 1.0, 0.0), 60.0, height=height, width=width)


def render(args, source: str, seed: int, device) -> FitView:
    """The reference view of ``source`` (a built-in scene or ``mesh:FILE``) with ``seed``, with its
    back-face layer (ray-traced once into ``CACHE/backface/``)."""
    from torch_ao.reference import render_reference

    w, h = (int(x) for x in args.size.lower().split("x"))
    mesh = Path(source[5:]) if source.startswith("mesh:") else None
    stem = source if mesh is None else f"mesh_{mesh.parent.name}_{mesh.stem}"
    path = Path(args.cache or default_cache_dir()) / "backface" / f"{stem}_{w}x{h}_spp{args.spp}_R{args.max_distance:g}_s{seed}.npz"
    if not path.exists():
        scene, views = _scene_and_views(source, seed, w, h)
        ref = render_reference(scene, views, spp=args.spp, max_distance=args.max_distance, seed=seed, uniform=False,
                               backface=True, progress=False)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + f".tmp{os.getpid()}.npz")
        ref.save(tmp)
        os.replace(tmp, path)
    view = load_views([path], device=device)[0]
    view.name = f"{source.replace('mesh:', '')}/s{seed}"
    return view


def sources(args, holdout: bool = False) -> list[str]:
    scenes = [s for s in args.scenes.split(",") if s]
    meshes = [m for m in (args.holdout_meshes if holdout else args.meshes).split(",") if m]
    return scenes + ["mesh:" + m for m in meshes]


def epoch_views(args, epoch: int) -> list[tuple[str, int]]:
    """The (source, seed) pairs of ``epoch``, shuffled (same list on every rank)."""
    g = torch.Generator().manual_seed(args.seed * 7919 + epoch)
    pairs = []
    for source in sources(args):
        first = epoch * args.views_per_scene
        pairs += [(source, 1 + (first + i) % args.seed_pool) for i in range(args.views_per_scene)]
    return [pairs[i] for i in torch.randperm(len(pairs), generator=g).tolist()]


def shard(items: list, steps: int, batch: int, rank: int, world: int) -> list[list]:
    """``steps`` batches of ``batch`` items for ``rank`` (items padded by wrapping around, so that
    every rank runs the same number of steps -- DDP needs that)."""
    need = steps * batch * world
    padded = [items[i % len(items)] for i in range(need)]
    mine = padded[rank::world]
    return [mine[i * batch:(i + 1) * batch] for i in range(steps)]


def target_thickness(gbuffer, cap: float) -> torch.Tensor:
    """``(B,1,H,W)`` true back-face thickness ``backface_depth - depth`` (world units), at most ``cap``
    (also where the ray has no exit); 0 on background pixels."""
    t = (gbuffer.backface_depth - gbuffer.safe_depth).clamp(0.0, cap)
    return torch.where(gbuffer.valid, t, torch.zeros_like(t))


# ---------------------------------------------------------------------------------------------
# Distributed set-up and checkpoints
# ---------------------------------------------------------------------------------------------
def setup_distributed():
    """(rank, world size, device); under torchrun, the process group (torch_ao.distributed)."""
    device = "cuda" if torch.cuda.is_available() else "cpu"
    ranks.init_from_environment(device)
    return ranks.rank(), ranks.world_size(), ranks.rank_device(device)


def weights_checksum(model: nn.Module) -> str:
    h = hashlib.sha256()
    for name, p in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(p.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------
# Training and evaluation
# ---------------------------------------------------------------------------------------------
def batch_loss(ao: nn.Module, net: nn.Module, views: list[FitView], radius: float, cap: float, supervised: bool) -> torch.Tensor:
    """Mean over ``views`` of the stage's L1 loss on valid pixels: against the capped back-face thickness
    in units of R (``supervised``), else of soft bitmask AO with the net's thickness map against the
    reference. The net (a :class:`ThicknessCNN`, maybe DDP-wrapped) runs once on the stacked features of
    all views (DDP wants one forward per backward); its output is thickness in units of ``radius``,
    as :class:`NetThickness` reads it."""
    x = torch.cat([net_features(v.gbuffer, radius).float() for v in views])
    maps = (radius * net(x)).split([v.gbuffer.depth.shape[0] for v in views])
    losses = []
    for view, t in zip(views, maps):
        valid = view.gbuffer.valid
        if supervised:
            target = target_thickness(view.gbuffer, cap * radius).to(t.dtype)
            losses.append(((t - target) / radius)[valid].abs().mean())
        else:
            ao.thickness = t.to(view.gbuffer.depth.dtype)
            losses.append((ao(view.gbuffer).visibility - view.reference)[valid].abs().mean())
    return torch.stack(losses).mean()


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes to train and evaluate on")
    p.add_argument("--meshes", default=",".join(TRAIN_MESHES), help=f"mesh files to train on (relative to {MESH_DIR})")
    p.add_argument("--holdout-meshes", default=",".join(HOLDOUT_MESHES), help="mesh files to evaluate on, never trained on")
    p.add_argument("--views-per-scene", type=int, default=2, help="training views per scene or mesh and epoch")
    p.add_argument("--seed-pool", type=int, default=4, help="distinct random seeds per scene (epochs cycle through them)")
    add_view_options(p, size="96x54", spp=256, max_distance=0.5, radius_note=" (also the method's radius and the net's scale)",
                     holdout_note="per scene and mesh (seeds 1000, 1001, ...)")
    p.add_argument("--cap", type=float, default=2.0, help="back-face thickness cap, in units of R")
    p.add_argument("--preset", default="medium", help="bitmask quality preset of the end-to-end stage")
    p.add_argument("--eval-preset", default="high", help="bitmask quality preset of the evaluation")
    p.add_argument("--weighting", default="cosine", choices=("uniform", "cosine"))
    p.add_argument("--fetch", default="edge_aware", choices=("bilinear", "edge_aware"),
                   help="bitmask AO's depth fetch (stage b and the evaluation): with bilinear's skirts across depth "
                        "edges even the true back-face layer loses to one scalar thickness")
    p.add_argument("--epochs", type=int, default=12, help="epochs of stage a (supervised on the back-face thickness)")
    p.add_argument("--finetune-epochs", type=int, default=0, help="epochs of stage b (end-to-end through soft bitmask AO; "
                   "the net after stage a is then evaluated too)")
    p.add_argument("--batch", type=int, default=2, help="views per step and rank")
    p.add_argument("--lr", type=float, default=5e-3)
    p.add_argument("--finetune-lr", type=float, default=1e-3)
    p.add_argument("--width", type=int, default=16, help="channels of the CNN")
    p.add_argument("--init", type=float, default=0.5, help="thickness the untrained net outputs everywhere, in units of R")
    p.add_argument("--tau", default="0.5,0.1", help="stage b's soft temperature schedule start,end (sector units, geometric)")
    p.add_argument("--scalar", type=float, default=None, help="scalar thickness (world units) to compare with (default: grid search)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=2, help="steps between checkpoints")
    p.add_argument("--out", default="runs/thickness_net", help="output folder")
    p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (for tests of resuming)")
    p.add_argument("--no-eval", action="store_true", help="skip the held-out evaluation")
    p.add_argument("--tiny", action="store_true", help="smoke test (options left at their defaults are replaced): 2 scenes, "
                   "no meshes unless given, 32x24, 16 spp, low presets, 2 + 1 epochs")
    return apply_tiny(p, p.parse_args(argv), scenes="fence,floating", meshes="", holdout_meshes="", size="32x24", spp=16,
                      preset="low", eval_preset="low", views_per_scene=2, seed_pool=2, epochs=2, finetune_epochs=1, batch=1)


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
    net = ThicknessCNN(args.width, args.init).to(device)
    model = nn.parallel.DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None) \
        if world > 1 else net
    optimizer = torch.optim.Adam(net.parameters(), lr=args.lr)
    ao = get_method("bitmask")(preset=args.preset, radius=R, weighting=args.weighting, mode="soft", tau=tau0, fetch=args.fetch,
                               thickness=torch.ones(1, 1, 1, 1), trainable=False).to(device)

    per_epoch = math.ceil(len(epoch_views(args, 0)) / (args.batch * world))
    supervised_steps = per_epoch * args.epochs
    total = per_epoch * (args.epochs + args.finetune_epochs)
    ckpt = out / "checkpoint.pt"
    fingerprint = {k: v for k, v in vars(args).items() if k not in ("out", "cache", "max_steps", "no_eval", "checkpoint_every",
                                                                     "scalar", "eval_preset", "holdout_meshes", "holdout_views")}
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
    say(f"training NetThickness's CNN ({sum(p.numel() for p in net.parameters())} weights) on {world} process(es), "
        f"{device.type}: {args.epochs} supervised + {args.finetune_epochs} end-to-end epochs x {per_epoch} steps x "
        f"{args.batch} views/rank, {args.size}, {len(sources(args))} scenes and meshes")

    seen = []
    t_start, cpu_start = time.perf_counter(), time.process_time()
    stop = total if args.max_steps is None else min(total, args.max_steps)
    while step < stop:
        epoch, k = divmod(step, per_epoch)
        batch = shard(epoch_views(args, epoch), per_epoch, args.batch, rank, world)[k]
        views = [render(args, s, seed, device) for s, seed in batch]
        supervised = step < supervised_steps
        for group in optimizer.param_groups:
            group["lr"] = args.lr if supervised else args.finetune_lr
        progress = (step - supervised_steps) / max(1, total - supervised_steps - 1)
        ao.tau = math.exp(math.log(tau0) + (math.log(tau1) - math.log(tau0)) * max(0.0, progress))
        optimizer.zero_grad(set_to_none=True)
        loss = batch_loss(ao, model, views, R, args.cap, supervised)
        loss.backward()  # DDP averages the gradients over ranks here
        optimizer.step()
        seen += [v.name for v in views]
        mean_loss = ranks.sum_over_ranks(loss.detach().double().reshape(1)) / world
        stage = "supervised" if supervised else "end-to-end"
        history.append({"step": step, "epoch": epoch, "stage": stage, "loss": float(mean_loss), "tau": ao.tau})
        if step % max(1, total // 20) == 0 or step == total - 1 or step == supervised_steps:
            say(f"step {step + 1}/{total}  epoch {epoch}  {stage} loss {float(mean_loss):.4f}", flush=True)
        step += 1
        if rank == 0 and step == supervised_steps and args.finetune_epochs > 0:  # stage a's net, for comparison
            NetThickness(R, cnn=net).save(out / STAGE_A)
        if step % args.checkpoint_every == 0 or step == stop:
            states = ranks.gather_objects(rng_state())
            if rank == 0:
                save_checkpoint(ckpt, {"config": fingerprint, "model": net.state_dict(), "optimizer": optimizer.state_dict(),
                                       "step": step, "history": history, "rng": states})
    seconds, cpu_seconds = time.perf_counter() - t_start, time.process_time() - cpu_start

    checksum = weights_checksum(net)
    save_json(out / f"rank{rank}.json", {"rank": rank, "world_size": world, "steps": step, "views_seen": seen, "checksum": checksum,
                 "backend": dist.get_backend() if world > 1 else None})
    ranks.finish()  # (the evaluation below needs no collectives: the other ranks need not wait for it)
    result = None
    if rank == 0 and step == total:
        NetThickness(R, cnn=net).save(out / "thickness_net.pt")
        result = {"steps": step, "world_size": world, "train_seconds": seconds, "train_cpu_seconds": cpu_seconds,
                  "history": history, "checksum": checksum}
        if not args.no_eval:
            stage_a = out / STAGE_A if args.finetune_epochs > 0 and (out / STAGE_A).exists() else None
            result.update(evaluate_holdout(args, net, device, stage_a))
        save_json(out / "result.json", result)
        say(f"wrote {out / 'thickness_net.pt'}, {out / 'result.json'}")
    return result


def pipeline(args, thickness) -> DenoisedAO:
    """Bitmask AO at ``--eval-preset`` with ``thickness`` (a number or a model), followed by the denoiser."""
    method = get_method("bitmask")(preset=args.eval_preset, radius=args.max_distance, weighting=args.weighting,
                                   thickness=thickness, fetch=args.fetch, trainable=False)
    return DenoisedAO(method, denoiser=True)


def thickness_error(model: NetThickness, views: list[FitView], cap: float) -> dict:
    """Thickness MAE (world units and in units of R) of ``model``'s maps against the capped true back-face
    thickness, on valid pixels of all ``views``, and the same for the constant ``init``."""
    pred, true = [], []
    with torch.no_grad():
        for v in views:
            pred.append(model.predict(v.gbuffer)[v.gbuffer.valid].double())
            true.append(target_thickness(v.gbuffer, cap)[v.gbuffer.valid].double())
    pred, true = torch.cat(pred), torch.cat(true)
    return {"mae": float((pred - true).abs().mean()), "mae_over_R": float((pred - true).abs().mean() / model.scale),
            "true_median": float(true.median()), "pred_quantiles": torch.quantile(pred.float(), torch.tensor([0.05, 0.5, 0.95])).tolist()}


def evaluate_holdout(args, net: nn.Module, device, stage_a: Path | None = None) -> dict:
    """Held-out hard-mode AO error (with the denoiser) of the best scalar thickness, the untrained and the
    trained net (and the net after stage a, from the file ``stage_a``) and the true back-face layer, and the
    nets' thickness errors."""
    R, cap = args.max_distance, args.cap * args.max_distance
    held = [render(args, s, HOLDOUT_SEED + i, device) for s in sources(args, holdout=True) for i in range(args.holdout_views)]
    net.eval()
    trained = NetThickness(R, cnn=net)
    untrained = NetThickness(R, init=args.init * R)
    if args.scalar is not None:
        scalar, grid = args.scalar, {}
    else:  # the best single thickness on (the first epoch's) training views, hard mode, with the denoiser
        train = [render(args, s, seed, device) for s, seed in epoch_views(args, 0)]
        grid = {t * R: evaluate(pipeline(args, t * R), train)["mae"] for t in (0.1, 0.25, 0.5, 1.0, 2.0, 4.0)}
        scalar = min(grid, key=grid.get)
    with torch.no_grad():
        rows = {"untrained net (init everywhere)": evaluate(pipeline(args, untrained), held),
                f"best scalar ({scalar:g})": evaluate(pipeline(args, scalar), held),
                "thickness net": evaluate(pipeline(args, trained), held),
                "true back-face layer": evaluate(pipeline(args, BackfaceThickness()), held)}
        nets = {"thickness net": trained, "untrained net": untrained}
        if stage_a is not None:
            nets["net after stage a"] = NetThickness.load(stage_a)
            nets["net after stage a"].cnn.to(device)
            rows["thickness net after stage a (supervised only)"] = evaluate(pipeline(args, nets["net after stage a"]), held)
        per_view = {name: evaluate(pipeline(args, model), held, per_view=True)["views"]
                    for name, model in (("best scalar", scalar), ("thickness net", trained), ("true back-face layer", BackfaceThickness()))}
    thickness = {name: thickness_error(model, held, cap) for name, model in nets.items()}
    print(f"\n{'held-out views, hard mode, ' + args.eval_preset + ' + denoiser':<48}{'MAE':>8}{'RMSE':>8}{'PSNR':>8}{'SSIM':>8}")
    for name, r in rows.items():
        print(f"{name:<48}{r['mae']:8.4f}{r['rmse']:8.4f}{r['psnr']:8.2f}{r['ssim']:8.4f}")
    for name, r in thickness.items():
        print(f"thickness MAE of the {name} against the true back-face thickness (capped at {cap:g}): "
              f"{r['mae']:.4f} ({r['mae_over_R']:.3f} R; true median {r['true_median']:.3f})")
    q = thickness["thickness net"]["pred_quantiles"]
    print(f"predicted thickness on held-out valid pixels: 5% {q[0]:.3f}, median {q[1]:.3f}, 95% {q[2]:.3f}")
    return {"holdout": rows, "holdout_per_view": per_view, "thickness_error": thickness, "scalar": scalar,
            "scalar_grid_train_mae": {f"{k:g}": v for k, v in grid.items()}, "holdout_thickness_quantiles": q,
            "holdout_views": [v.name for v in held]}


if __name__ == "__main__":
    main()
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # every file is written: leave without finalising, under gloo threads that DDP keeps alive
        # (torch_ao.distributed.finish says why that can abort a rank)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)

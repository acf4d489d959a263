"""Fitting an AO module's float parameters to ray-traced reference visibility.

The loop is plain Adam (by default) on the chosen ``nn.Parameter``s, with

* a loss on valid pixels only (L1, MSE or ``psnr``, optionally weighted by ``1/(stderr^2 + eps)``); ``psnr`` is
  each view's ``10 log10(MSE)``, the negative of its PSNR, so the views are averaged in decibels as the reports
  average them and a view that is already close to its reference is not outweighed by the others' larger errors,
* a temperature schedule for soft-mask modules (geometric from ``temperature_start`` to
  ``temperature_end``; the module is put in ``mode="soft"`` while fitting),
* gradient clipping, projection onto each parameter's valid range, early stopping,
* a hard-mode score of the parameters on all views at the start, every ``hard_every`` steps and at
  the end (modules with a soft mode are put in hard mode for it; others are scored as they run); the
  best-scoring parameters are kept (the soft objective's optimum is not always the shipped
  pipeline's), stopping after ``hard_patience`` scores without improvement (the fit has converged),
* a step budget that grows while the fit improves: when ``steps`` are done and the best hard-mode
  score is the latest one, or fewer than ``hard_patience`` scores since the best have missed it, the fit
  goes on (``hard_every * max(1, hard_patience)`` steps at a time) up to ``max_steps``;
  :attr:`FitResult.converged` says whether it stopped by convergence,
* atomic checkpoints (parameters, optimizer state, step, RNG state, history) every
  ``checkpoint_every`` steps; the same call with the same ``checkpoint`` path resumes and ends
  with the same result as an uninterrupted run. A checkpoint records the fingerprint of everything
  that determines the result (:func:`run_fingerprint`: the config, the caller's settings, the module's
  structure and start values, the training views' data); one written by a run that differs in any
  of them is refused with :class:`CheckpointMismatch`, which names what differs,
* views taken one at a time (``views[i]``), so a sequence that reads them on access
  (:class:`~torch_ao.fit_data.ViewFiles`) holds a few in memory, with the same losses as a list,
* data-parallel ranks under ``torchrun`` (:mod:`torch_ao.distributed`): each rank runs its shard of a
  step's views and of the hard-mode scores, and the gradients and losses are summed over the ranks.

Evaluation is always in **hard** mode (what an engine ships) with :func:`evaluate`.
"""
from __future__ import annotations

import hashlib
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from .checks import check_choice
from .distributed import broadcast_object, gather_objects, is_distributed, is_main, shard, sum_over_ranks
from .io import remove_stale_temporaries as remove_stale_files
from .io import write_atomic
from .metrics import error_metrics
from .views import FitView, load_views

__all__ = ["FitView", "FitConfig", "FitResult", "fit", "evaluate", "load_views", "set_mode", "rng_state",
           "set_rng_state", "save_checkpoint", "load_checkpoint", "remove_stale_temporaries", "fittable_parameters",
           "CheckpointMismatch", "run_fingerprint", "fingerprint_differences", "checkpoint_settings_differences"]

#: Bounds applied after every optimizer step (parameters outside them are meaningless). A falloff
#: range of exactly 0 is GTAO's hard cut, where neither radius nor falloff has a gradient.
PARAMETER_MINIMUM = {"thickness": 0.0, "thickness_scale": 0.0, "thickness_slope": 0.0, "radius": 1e-3, "falloff_range": 1e-2, "final_power": 0.05, "albedo": 0.0,
                     "angle_bias": 0.0, "thickness_heuristic": 0.0, "thickness_growth": 0.0}
PARAMETER_MAXIMUM = {"falloff_range": 1.0, "thickness_heuristic": 1.0, "albedo": 1.0, "angle_bias": math.pi / 2 - 1e-3}


#: losses against the reference: per pixel (``l1``, ``mse``) or per view (``psnr``: minus its PSNR in dB)
LOSSES = ("l1", "mse", "psnr")

#: The smallest MSE the ``psnr`` loss tells apart: PSNR 100 dB, where :func:`error_metrics` caps it.
PSNR_MSE_FLOOR = 1e-10


@dataclass
class FitConfig:
    """Settings of :func:`fit` (all serialisable, so a checkpoint can check it resumes the same run)."""

    params: Sequence[str] = ("thickness",)
    steps: int = 100
    lr: float = 0.05
    loss: str = "l1"  # one of LOSSES
    weight_by_stderr: bool = False
    batch_views: int = 0  # views per step (0 = all)
    temperature_start: float = 0.5
    temperature_end: float = 0.05
    clip_grad: float = 1.0
    patience: int = 0  # early stop after this many steps without improvement (0 = never)
    min_delta: float = 1e-6
    seed: int = 0
    checkpoint_every: int = 10
    #: Every ``hard_every`` steps (and before the first and after the last) the parameters are scored
    #: in hard mode (what ships) on all training views, and the best hard-mode parameters are kept
    #: (0 = keep the best soft-mode loss instead).
    hard_every: int = 10
    #: Stop once this many hard-mode scores in a row have not improved on the best (0 = never).
    hard_patience: int = 0
    #: With ``hard_patience``: stop only once the soft loss has plateaued too, i.e. its mean over the
    #: last ``hard_every`` steps is less than this fraction below the mean over the ``hard_every``
    #: before (0 = the hard-mode scores alone decide).
    plateau: float = 0.0
    #: Largest number of steps: while the best hard-mode score is the latest one, or ``hard_patience`` has
    #: not run out, when the budget (``steps``, then each extension) is spent, the fit goes on, up to this
    #: many (0 = ``steps``).
    max_steps: int = 0
    #: Learning rate per parameter name (last part, e.g. ``{"radius": 0.01}``) replacing ``lr``.
    param_lr: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.params = tuple(self.params)
        check_choice("loss", self.loss, LOSSES)
        if self.steps < 0 or self.lr <= 0:
            raise ValueError(f"steps/lr: expected steps >= 0 and lr > 0, got {self.steps}, {self.lr}")
        if not (self.temperature_start > 0 and self.temperature_end > 0):
            raise ValueError("temperature_start/temperature_end: expected > 0")
        if self.hard_every < 0 or self.hard_patience < 0:
            raise ValueError(f"hard_every/hard_patience: expected integers >= 0, got {self.hard_every}, {self.hard_patience}")
        if not self.plateau >= 0:
            raise ValueError(f"plateau: expected a fraction >= 0, got {self.plateau}")
        if self.max_steps and self.max_steps < self.steps:
            raise ValueError(f"max_steps: expected 0 or at least steps ({self.steps}), got {self.max_steps}")
        self.param_lr = {str(k): float(v) for k, v in dict(self.param_lr).items()}
        if any(not v > 0 for v in self.param_lr.values()):
            raise ValueError(f"param_lr: expected learning rates > 0, got {self.param_lr}")


@dataclass
class FitResult:
    parameters: dict[str, list | float]
    history: list[dict] = field(default_factory=list)
    steps_done: int = 0
    stopped_early: bool = False
    seconds: float = 0.0
    #: Hard-mode losses on all training views: ``[{"step", "loss", <parameter values>}]``.
    hard_history: list[dict] = field(default_factory=list)
    #: Step whose parameters the module holds at the end (``None``: the last ones).
    best_step: int | None = None
    #: Whether the fit stopped because it converged (``hard_patience`` hard-mode scores without
    #: improvement and the soft loss plateaued, or ``patience`` soft-mode steps without improvement)
    #: rather than at its step limit.
    converged: bool = False
    #: The step budget at the end: ``steps``, or more where the fit was extended (``max_steps``).
    step_limit: int = 0

    @property
    def best_at_limit(self) -> bool:
        """Whether the kept parameters are the latest hard-mode score's of a fit that did not converge:
        more steps would likely improve it."""
        return not self.converged and self.best_step is not None and bool(self.hard_history) \
            and self.best_step == self.hard_history[-1]["step"]


def set_mode(module: nn.Module, mode: str | None, temperature: float | None = None) -> None:
    """Put soft-mask modules (those with a ``mode`` attribute, e.g. ``BitmaskAO``) in ``mode``, with
    soft-mask temperature ``tau = temperature`` (in sectors)."""
    for m in module.modules():
        if mode is not None and hasattr(m, "mode"):
            m.mode = mode
        if temperature is not None and hasattr(m, "tau"):
            m.tau = float(temperature)


def _named_fit_parameters(module: nn.Module, names: Sequence[str]) -> dict[str, nn.Parameter]:
    """``{name: parameter}``; a name is a full parameter name or the last part of exactly one
    (``thickness`` for a pipeline's ``method.thickness``)."""
    available = dict(module.named_parameters())
    chosen = {}
    for name in names:
        matches = [name] if name in available else [k for k in available if k.endswith("." + name)]
        if len(matches) != 1:
            what = "is not a float parameter" if not matches else f"names several parameters ({', '.join(matches)})"
            raise ValueError(f"params: {name!r} {what} of {type(module).__name__}; "
                             f"available: {', '.join(sorted(available)) or 'none'}")
        chosen[name] = available[matches[0]]
    return chosen


def fittable_parameters(module: nn.Module) -> tuple[str, ...]:
    """Names (last part) of the float parameters ``module`` registers as ``nn.Parameter``: the ones
    that matter for its variant and options (methods register unused ones as frozen buffers)."""
    return tuple(name.rsplit(".", 1)[-1] for name, _ in module.named_parameters())


def _loss(pred: torch.Tensor, view: FitView, kind: str, weight_by_stderr: bool) -> torch.Tensor:
    valid = view.gbuffer.valid
    diff = (pred - view.reference)[valid]
    if not diff.numel():
        return pred.sum() * 0.0
    per_pixel = diff.abs() if kind == "l1" else diff.square()
    if weight_by_stderr and view.stderr is not None:
        w = 1.0 / (view.stderr[valid].square() + 1e-4)
        mean = (per_pixel * w).sum() / w.sum().clamp_min(1e-12)
    else:
        mean = per_pixel.mean()
    return 10.0 * torch.log10(mean + PSNR_MSE_FLOOR) if kind == "psnr" else mean


def _temperature(cfg: FitConfig, step: int) -> float:
    if cfg.steps <= 1:
        return cfg.temperature_end
    t = min(1.0, step / (cfg.steps - 1))  # (steps past the budget keep the final temperature)
    return math.exp((1 - t) * math.log(cfg.temperature_start) + t * math.log(cfg.temperature_end))


def rng_state() -> dict:
    """The torch (and CUDA), numpy and Python RNG states, in a form ``torch.load(weights_only=True)`` reads."""
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state()[1].tolist(),
             "numpy_pos": int(np.random.get_state()[2]), "python": list(random.getstate()[1]),
             "python_pos": random.getstate()[2]}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state()
    return state


def set_rng_state(state: dict) -> None:
    """Restore what :func:`rng_state` saved."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", np.array(state["numpy"], dtype=np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((3, tuple(state["python"]), state["python_pos"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state(state["cuda"])


def save_checkpoint(path: Path, payload: dict) -> None:
    """``torch.save`` to a temporary file in the same folder, then an atomic rename (:func:`~torch_ao.io.write_atomic`)."""
    write_atomic(path, lambda tmp: torch.save(payload, tmp))


def remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files a run killed inside :func:`save_checkpoint` left next to ``path`` (the
    checkpoint itself is always whole: it is replaced by an atomic rename); a concurrent writer's file
    in progress is kept (:func:`~torch_ao.io.remove_stale_temporaries`)."""
    path = Path(path)
    remove_stale_files(path.parent, path.name)


class CheckpointMismatch(ValueError):
    """A checkpoint written by a run with other settings; ``differences`` names them
    (:func:`fingerprint_differences`)."""

    def __init__(self, path: str | os.PathLike, differences) -> None:
        self.path, self.differences = Path(path), tuple(differences)
        super().__init__(f"checkpoint: {path} was written with other settings ({', '.join(self.differences)}); "
                         "remove it or use another path")


def _digest(items) -> str:
    """SHA-256 (hex, 16 digits) of tensors (dtype, shape and bytes) and other values (their ``repr``)."""
    h = hashlib.sha256()
    for item in items:
        if isinstance(item, torch.Tensor):
            t = item.detach().cpu().contiguous()
            h.update(f"{t.dtype}{tuple(t.shape)}".encode())
            h.update((t.float() if t.dtype in (torch.float16, torch.bfloat16) else t).numpy().tobytes())
        else:
            h.update(repr(item).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


def _view_digest(view: FitView) -> str:
    gb = view.gbuffer
    return _digest([view.name, gb.depth, gb.normals, gb.light, gb.mask, gb.object_id, gb.backface_depth, gb.position,
                    gb.camera.intrinsics, view.reference, view.stderr])


def run_fingerprint(module: nn.Module, views: Sequence[FitView], cfg: FitConfig, settings: dict | None = None, *,
                    distributed: bool = False) -> dict:
    """What determines a :func:`fit`'s result, as values a checkpoint stores and compares.

    ``config``: ``cfg``'s fields (but ``checkpoint_every``); ``settings``: the caller's named settings
    (JSON values: what built the module and the views, e.g. scenes, size, preset); ``module``: a digest
    of the module's structure (its ``repr``) and start values (``state_dict``); ``views``: a digest of
    the training views' names and data (G-buffer layers, intrinsics, references, standard errors: a digest
    of each view's digest, each view read once); ``torch_ao_version``. ``distributed``: every rank of the
    process group calls it and digests its shard of the views (:func:`~torch_ao.distributed.shard`); all
    get the same value as one process.
    """
    from .version import __version__

    state = module.state_dict()
    indices = list(range(len(views)))
    digests = {}
    for part in gather_objects({i: _view_digest(views[i]) for i in (shard(indices) if distributed else indices)}):
        digests.update(part)
    return {"config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items() if k != "checkpoint_every"},
            "settings": dict(settings or {}),
            "module": _digest([repr(module), *(x for k, t in state.items() for x in (k, t))]),
            "views": _digest([digests[i] for i in indices]), "torch_ao_version": __version__}


def fingerprint_differences(saved: dict | None, current: dict) -> list[str]:
    """What differs between two :func:`run_fingerprint` values, most specific cause first: the
    ``settings`` keys that differ; when none do, the ``config`` fields; when none do, ``module``,
    ``views`` and ``torch_ao_version`` (``[]``: the same run). ``saved=None`` (a checkpoint without a
    fingerprint, from an older torch_ao) is ``["torch_ao_version"]``."""
    if not isinstance(saved, dict):
        return ["torch_ao_version"]
    for group in ("settings", "config"):
        names = _changed(saved.get(group) or {}, current[group])
        if names:
            return names
    return [k for k in ("module", "views", "torch_ao_version") if saved.get(k) != current[k]]


def checkpoint_settings_differences(path: str | os.PathLike, settings: dict) -> list[str]:
    """The ``settings`` keys in which the checkpoint at ``path`` was written with other values
    (``["torch_ao_version"]`` for one without a fingerprint; ``[]`` when there is no checkpoint): a
    caller can refuse a checkpoint of other settings before building the views and the module."""
    path = Path(path)
    if not path.exists():
        return []
    saved = load_checkpoint(path).get("fingerprint")
    if not isinstance(saved, dict):
        return ["torch_ao_version"]
    return _changed(saved.get("settings") or {}, settings)


def _changed(old: dict, new: dict) -> list[str]:
    """Keys (``new``'s order, then ``old``'s) whose values differ, a missing key counting as ``None``."""
    return [k for k in dict.fromkeys([*new, *old]) if old.get(k) != new.get(k)]


def load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupted or foreign file
        raise ValueError(f"checkpoint: cannot read {path} ({err})") from None


def fit(module: nn.Module, views: Sequence[FitView], config: FitConfig | None = None, *,
        checkpoint: str | os.PathLike | None = None, progress: bool = True, settings: dict | None = None,
        distributed: bool | None = None) -> FitResult:
    """Fit ``config.params`` of ``module`` to the reference visibility of ``views``.

    Args:
        module: any AO module returning :class:`~torch_ao.methods.AOOutput` (or a visibility tensor),
            e.g. a method or a :class:`~torch_ao.fitted.FittedPipeline` (method + denoiser).
        views: training views (see :class:`FitView`, :func:`load_views`): a list, or any sequence whose items
            are read on access (:class:`~torch_ao.fit_data.ViewFiles`); each step takes ``views[i]`` once
            per view, so only the view in use (and what the sequence caches) is in memory.
        config: :class:`FitConfig`.
        checkpoint: file to write checkpoints to and resume from; one written by a run with another
            :func:`run_fingerprint` raises :class:`CheckpointMismatch` before anything is changed.
        progress: show a tqdm progress bar.
        settings: named JSON values that built ``module`` and ``views`` (e.g. ``{"scenes": ...,
            "preset": ...}``), stored in the checkpoint's fingerprint so that a mismatch names them.
        distributed: data-parallel over the ranks of the ``torch.distributed`` process group (``None``: when
            one of more than one rank is running, e.g. under ``torchrun``; every rank then calls :func:`fit`
            with the same arguments). Each rank runs its shard of each step's views
            (:func:`~torch_ao.distributed.shard`) and of the hard-mode scores; gradients and losses are
            summed over the ranks, so every rank takes the same step and the result is one process's up to
            the order of the float sums. Only rank 0 shows progress and writes the checkpoint; on resume
            rank 0 reads it and sends it to the others.

    Returns:
        :class:`FitResult` with the fitted parameter values, the loss history and timings.
        At the end the module holds, when ``hard_every > 0``, the
        parameters with the lowest **hard-mode** loss on all views among the start, every
        ``hard_every``-th step and the end (so the result is never worse in hard mode on the training
        views than the start); otherwise the parameters of the lowest training loss, or the last ones
        when each step sees only a batch of the views.

    Shape:
        - views: each a :class:`FitView`: a :class:`~torch_ao.GBuffer` ``(B, C, H, W)`` and its reference
          visibility ``(B, 1, H, W)`` in [0, 1] (optional stderr the same shape).
        - module: returns visibility ``(B, 1, H, W)`` for such a G-buffer.
    """
    cfg = config or FitConfig()
    if not views:
        raise ValueError("views: expected at least one reference view")
    params = _named_fit_parameters(module, cfg.params)
    parallel = is_distributed() if distributed is None else bool(distributed) and is_distributed()
    main = not parallel or is_main()
    ckpt_path = Path(checkpoint) if checkpoint is not None else None
    if ckpt_path is not None:  # (before anything changes the module)
        fingerprint = run_fingerprint(module, views, cfg, settings, distributed=parallel)
    chosen = {id(p) for p in params.values()}
    for p in module.parameters():
        p.requires_grad_(id(p) in chosen)
    optimizer = torch.optim.Adam([{"params": [p], "lr": cfg.param_lr.get(name.rsplit(".", 1)[-1], cfg.lr)}
                                  for name, p in params.items()])
    hard = cfg.hard_every > 0
    state = {"step": 0, "history": [], "best_loss": math.inf, "best": None, "bad_steps": 0, "stopped_early": False,
             "hard": [], "best_hard": math.inf, "best_step": None, "limit": cfg.steps}
    saved = _read_checkpoint(ckpt_path, main, parallel) if ckpt_path is not None else None
    if saved is not None:
        differences = fingerprint_differences(saved.get("fingerprint"), fingerprint)
        if differences:
            raise CheckpointMismatch(ckpt_path, differences)
        try:
            module.load_state_dict(saved["module"])
            optimizer.load_state_dict(saved["optimizer"])
        except (KeyError, RuntimeError, ValueError) as err:  # same fingerprint, yet not this module's state
            raise CheckpointMismatch(ckpt_path, ["module"]) from err
        set_rng_state(saved["rng"])
        state = saved["state"]
        state.setdefault("limit", cfg.steps)
    else:
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)

    def snapshot():
        return {"fingerprint": fingerprint, "module": module.state_dict(), "optimizer": optimizer.state_dict(),
                "rng": rng_state(), "state": state}

    def values() -> dict[str, torch.Tensor]:
        return {n: p.detach().clone() for n, p in params.items()}

    def check_hard() -> None:
        """Score the current parameters in hard mode on every view; keep them if they are the best."""
        if state["hard"] and state["hard"][-1]["step"] == state["step"]:
            return  # already scored (a resumed, finished run)
        set_mode(module, "hard")
        indices = list(range(len(views)))
        loss = 0.0
        with torch.no_grad():
            for i in (shard(indices) if parallel else indices):
                view = views[i]
                loss += float(_loss(_visibility(module(view.gbuffer)), view, cfg.loss, cfg.weight_by_stderr))
                del view
        if parallel:
            loss = float(sum_over_ranks(torch.tensor([loss], dtype=torch.float64))[0])
        loss /= len(views)
        state["hard"].append({"step": state["step"], "loss": loss,
                              **{n: p.detach().cpu().flatten().tolist() for n, p in params.items()}})
        if loss < state["best_hard"]:
            state["best_hard"], state["best"], state["best_step"] = loss, values(), state["step"]
            state["hard_bad"] = 0
        else:
            state["hard_bad"] = state.get("hard_bad", 0) + 1
            if cfg.hard_patience and state["hard_bad"] >= cfg.hard_patience and soft_plateaued():
                state["stopped_early"] = True

    def soft_plateaued() -> bool:
        """Whether the soft loss's mean over the last ``hard_every`` steps is within ``plateau`` of the one before."""
        if not cfg.plateau:
            return True
        w, losses = cfg.hard_every, [r["loss"] for r in state["history"]]
        if len(losses) < 2 * w:
            return False
        before, last = sum(losses[-2 * w:-w]) / w, sum(losses[-w:]) / w
        return before - last <= cfg.plateau * abs(before)

    def extend() -> bool:
        """At the step limit: raise it while the fit has not converged by its own rule, so that a limit never
        stops a fit that is still improving (the latest hard-mode score is the best, or fewer than
        ``hard_patience`` scores since the best have failed to improve on it), as ``max_steps`` allows."""
        latest_is_best = hard and state["hard"] and state["best_step"] == state["hard"][-1]["step"]
        patient = hard and cfg.hard_patience and state.get("hard_bad", 0) < cfg.hard_patience
        if not (latest_is_best or patient) or state["limit"] >= cfg.max_steps:
            return False
        state["limit"] = min(cfg.max_steps, state["limit"] + cfg.hard_every * max(1, cfg.hard_patience))
        if bar is not None:
            bar.total = state["limit"]
            bar.refresh()
        return True

    bar = None
    if progress and main:
        from tqdm.auto import tqdm

        bar = tqdm(total=state["limit"], initial=state["step"], desc="fit", unit="step", leave=False)
    start = time.perf_counter()
    partial = bool(cfg.batch_views) and cfg.batch_views < len(views)
    try:
        while not state["stopped_early"]:
            if state["step"] >= state["limit"]:
                if hard:
                    check_hard()  # the score at the limit decides whether to go on
                if state["stopped_early"] or not extend():
                    break
                continue
            step = state["step"]
            if hard and step % cfg.hard_every == 0:
                check_hard()
                if state["stopped_early"]:
                    break
            temperature = _temperature(cfg, step)
            set_mode(module, "soft", temperature)
            order = torch.randperm(len(views)).tolist()
            batch = order[: cfg.batch_views] if cfg.batch_views else order
            optimizer.zero_grad(set_to_none=True)
            total = 0.0
            for i in (shard(batch) if parallel else batch):
                view = views[i]
                loss = _loss(_visibility(module(view.gbuffer)), view, cfg.loss, cfg.weight_by_stderr) / len(batch)
                loss.backward()
                total += float(loss.detach())
                del view  # (before the next read: one view in memory at a time, besides a sequence's cache)
            if parallel:
                total = _sum_gradients_over_ranks(params, total)
            grads = [p.grad for p in params.values() if p.grad is not None]
            if grads and not all(bool(torch.isfinite(g).all()) for g in grads):
                raise FloatingPointError(f"fit: non-finite gradient at step {step}; lower lr or temperature_end")
            record = {"step": step, "loss": total, "temperature": temperature,
                      **{n: p.detach().cpu().flatten().tolist() for n, p in params.items()}}
            improved = total < state["best_loss"] - cfg.min_delta
            if improved:
                state["best_loss"], state["bad_steps"] = total, 0
                if not hard and not partial:
                    state["best"], state["best_step"] = values(), step  # the parameters this loss belongs to
            else:
                state["bad_steps"] += 1
                state["stopped_early"] = bool(cfg.patience) and state["bad_steps"] >= cfg.patience
            if cfg.clip_grad > 0:
                torch.nn.utils.clip_grad_norm_(list(params.values()), cfg.clip_grad)
            optimizer.step()
            with torch.no_grad():
                for name, p in params.items():
                    key = name.rsplit(".", 1)[-1]
                    if key in PARAMETER_MINIMUM or key in PARAMETER_MAXIMUM:  # others are unbounded (network weights)
                        p.clamp_(min=PARAMETER_MINIMUM.get(key), max=PARAMETER_MAXIMUM.get(key))
            # With partial batches a step's loss depends on its batch: keep the last parameters instead.
            if partial and not hard:
                state["best"], state["best_step"] = values(), step + 1
            state["history"].append(record)
            state["step"] = step + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{total:.4f}")
            if main and ckpt_path is not None and (state["step"] % cfg.checkpoint_every == 0
                                                   or state["step"] == state["limit"]):
                save_checkpoint(ckpt_path, snapshot())
        if hard:
            check_hard()
    finally:
        if bar is not None:
            bar.close()
    if main and ckpt_path is not None:
        save_checkpoint(ckpt_path, snapshot())
    if state["best"] is not None:
        with torch.no_grad():
            for name, p in params.items():
                p.copy_(state["best"][name])
    set_mode(module, "hard")
    values_out = {n: (p.detach().cpu().item() if p.numel() == 1 else p.detach().cpu().flatten().tolist()) for n, p in params.items()}
    return FitResult(values_out, state["history"], state["step"], state["stopped_early"], time.perf_counter() - start,
                     hard_history=state["hard"], best_step=state["best_step"], converged=state["stopped_early"],
                     step_limit=state["limit"])


def _read_checkpoint(path: Path, main: bool, parallel: bool) -> dict | None:
    """The checkpoint at ``path`` (``None`` when there is none), read by rank 0 (which first removes stale
    temporaries) and, in a data-parallel fit, sent to every rank; an unreadable file raises on every rank."""
    saved = None
    if main:
        remove_stale_temporaries(path)
        try:
            saved = load_checkpoint(path) if path.exists() else None
        except ValueError as err:
            saved = err
    if parallel:
        saved = broadcast_object(saved)
    if isinstance(saved, ValueError):
        raise saved
    return saved


def _sum_gradients_over_ranks(params: dict[str, nn.Parameter], loss: float) -> float:
    """Replace each parameter's gradient by its sum over the ranks (``None`` where no rank has one, as in
    one process) and return the sum of ``loss`` over the ranks."""
    ps = list(params.values())
    device = ps[0].device
    flat = torch.cat([torch.tensor([p.grad is not None for p in ps], dtype=torch.float64, device=device),
                      *((p.grad if p.grad is not None else torch.zeros_like(p)).detach().flatten().double() for p in ps),
                      torch.tensor([loss], dtype=torch.float64, device=device)])
    summed = sum_over_ranks(flat)
    offset = len(ps)
    for k, p in enumerate(ps):
        part = summed[offset:offset + p.numel()]
        p.grad = part.reshape(p.shape).to(device=p.device, dtype=p.dtype) if summed[k] > 0 else None
        offset += p.numel()
    return float(summed[-1])


def _visibility(out) -> torch.Tensor:
    return out.visibility if hasattr(out, "visibility") else out


@torch.no_grad()
def evaluate(module: nn.Module, views: Sequence[FitView], *, mode: str | None = "hard", repeats: int = 1,
             per_view: bool = False, distributed: bool = False) -> dict:
    """Error of ``module`` (in ``mode``, hard by default) against the views' references, and run time.

    Returns mean ``mae``, ``rmse``, ``psnr``, ``ssim`` over views and ``seconds`` (median forward time
    per view over ``repeats`` runs of each); with ``per_view``, also ``views``: ``{view name: metrics}``.
    ``views`` may be read on access (:class:`~torch_ao.fit_data.ViewFiles`). ``distributed``: every rank of
    the process group calls it; each scores its shard of the views and all return the same dict.

    Shape:
        - views: as :func:`fit` (G-buffers ``(B, C, H, W)``, references ``(B, 1, H, W)``).
        - Output: a dict of floats (``seconds`` in seconds).
    """
    if mode is not None:
        set_mode(module, mode)
    indices = list(range(len(views)))
    parallel = distributed and is_distributed()
    scored = {}  # index -> (name, metrics, forward times)
    for i in (shard(indices) if parallel else indices):
        view, times = views[i], []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            out = module(view.gbuffer)
            times.append(time.perf_counter() - t0)
        scored[i] = (view.name or str(i), error_metrics(_visibility(out), view.reference, view.gbuffer.valid), times)
        del view, out
    if parallel:
        for part in gather_objects(scored):
            scored.update(part)
    rows = [scored[i][1] for i in indices]
    result = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    result["seconds"] = float(np.median([t for i in indices for t in scored[i][2]]))
    if per_view:
        result["views"] = {scored[i][0]: scored[i][1] for i in indices}
    return result

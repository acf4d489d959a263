"""The training examples, run as a user runs them: subprocesses with tiny settings and a private
reference cache. Each asserts a real outcome (files written, fitted error on held-out views not
worse than the start), the thickness net resumes to the same weights after a real SIGKILL, and a
real 2-process DistributedDataParallel run (gloo on CPU) keeps identical weights on both ranks."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torch_ao.fit import evaluate
from torch_ao.fitted import load_fitted

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "training_examples"
SCRIPTS = ("fit_thickness.py", "fit_object_thickness.py", "train_thickness_net.py", "tune_gtao.py")


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """One reference cache for the module: the tiny views are ray-traced once."""
    return tmp_path_factory.mktemp("references")


def env(cache: Path) -> dict:
    e = dict(os.environ, TORCH_AO_CACHE=str(cache), OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    # the scripts' folder comes first on their import path: import this checkout's torch_ao, not an installed one
    e["PYTHONPATH"] = os.pathsep.join(filter(None, (str(ROOT), e.get("PYTHONPATH"))))
    e.pop("WORLD_SIZE", None)
    e.pop("RANK", None)
    return e


def run(script: str, *args, cache: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(EXAMPLES / script), *map(str, args)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env(cache), capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def finite(metrics: dict) -> bool:
    return all(math.isfinite(metrics[k]) for k in ("mae", "rmse", "psnr", "ssim"))


def test_every_example_documents_itself(cache):
    procs = {s: subprocess.Popen([sys.executable, str(EXAMPLES / s), "--help"], cwd=ROOT, env=env(cache),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for s in SCRIPTS}
    for script, proc in procs.items():
        doc = (EXAMPLES / script).read_text().split('"""')[1]
        for section in ("What it does", "How to run", "How to adapt"):
            assert section in doc, f"{script}: docstring lacks '{section}'"
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        assert "--tiny" in out and "--out" in out


def test_readme_has_a_paragraph_and_command_per_script():
    readme = (EXAMPLES / "README.md").read_text()
    for script in SCRIPTS:
        assert f"python training_examples/{script}" in readme, script


def test_fit_thickness(tmp_path, cache):
    out = tmp_path / "out"
    proc = run("fit_thickness.py", "--tiny", "--no-progress", "--out", out, cache=cache)
    assert "fitted thickness" in proc.stdout
    result = json.loads((out / "thickness.json").read_text())
    assert (out / "checkpoint.pt").exists()
    assert 0 < result["thickness"] < 10 and result["thickness"] != result["init"]
    before, after = result["holdout_before"], result["holdout_after"]
    assert finite(before) and finite(after)
    assert after["mae"] <= before["mae"] + 1e-6
    assert result["train_after"]["mae"] <= result["train_before"]["mae"] + 1e-6
    assert not set(result["train_views"]) & set(result["holdout_views"])
    # The same command again resumes from the finished checkpoint: same thickness, no new steps.
    run("fit_thickness.py", "--tiny", "--no-progress", "--out", out, cache=cache)
    again = json.loads((out / "thickness.json").read_text())
    assert again["thickness"] == result["thickness"] and again["steps"] == result["steps"]
    # params.json rebuilds the fitted pipeline (bitmask + denoiser): the same held-out numbers.
    pipeline = load_fitted(out / "params.json")
    assert pipeline.denoiser is not None and pipeline.method.thickness.item() == pytest.approx(result["thickness"])
    assert evaluate(pipeline, tiny_holdout(cache, "fence,room_corner"))["mae"] == pytest.approx(after["mae"], rel=1e-6)


def tiny_holdout(cache: Path, scenes: str) -> list:
    """The held-out views the examples use with --tiny (read from the module's cache)."""
    from torch_ao.datasets import train_and_holdout_views

    return train_and_holdout_views(scenes.split(","), 1, 1, height=24, width=32, spp=16, max_distance=1.0,
                                   cache_dir=cache)[1]


def test_fit_object_thickness(tmp_path, cache):
    out = tmp_path / "out"
    proc = run("fit_object_thickness.py", "--tiny", "--no-progress", "--out", out, cache=cache)
    result = json.loads((out / "object_thickness.json").read_text())
    names, table = result["names"], result["table"]
    assert len(table) == len(names) >= 3 and names[:2] == ["background", "plane"]
    shown = [n for n, share in zip(names, result["pixel_share"]) if share > 0]
    assert "plane" in shown and "thin box" in shown  # fence slats, floors and walls
    for name in shown:
        assert name in proc.stdout
    assert all(math.isfinite(t) and t >= 0 for t in table)
    rows = result["holdout"]
    start = rows[next(k for k in rows if k.startswith("scalar start"))]
    assert finite(rows["per-object fitted"])
    assert rows["per-object fitted"]["mae"] <= start["mae"] + 1e-6
    saved = json.loads((out / "params.json").read_text())
    assert saved["parameters"]["thickness"]["values"] == pytest.approx(table)
    assert saved["denoiser"] is not None and saved["names"] == names


def test_tune_gtao(tmp_path, cache):
    out = tmp_path / "out"
    proc = run("tune_gtao.py", "--tiny", "--no-progress", "--out", out, cache=cache)
    assert "XeGTAO" in proc.stdout
    result = json.loads((out / "gtao.json").read_text())
    rows = result["results"]
    assert rows["XeGTAO auto-tune"]["values"] == pytest.approx({"radius": 1.457, "falloff_range": 0.615, "final_power": 2.2})
    assert set(rows["fitted"]["values"]) == {"radius", "falloff_range", "final_power"}
    assert 0 < rows["fitted"]["values"]["falloff_range"] <= 1 and rows["fitted"]["values"]["final_power"] > 0
    assert rows["fitted"]["mae"] <= rows["fit start"]["mae"] + 1e-6
    assert result["radius_multiplier"] == pytest.approx(rows["fitted"]["values"]["radius"] / result["max_distance"])
    pipeline = load_fitted(out / "params.json")
    assert pipeline.method_name == "gtao" and pipeline.method.final_power.item() == pytest.approx(rows["fitted"]["values"]["final_power"])
    held = tiny_holdout(cache, "sphere_on_plane,room_corner")
    assert evaluate(pipeline, held)["mae"] == pytest.approx(rows["fitted"]["mae"], rel=1e-6)


def small_meshes(folder: Path) -> tuple[Path, Path]:
    """Two small mesh files (a box for training, an icosphere held out), so the test needs no system package."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    box, ball = folder / "box.obj", folder / "ball.obj"
    trimesh.creation.box(extents=(1.0, 0.4, 0.6)).export(box)
    trimesh.creation.icosphere(subdivisions=2).export(ball)
    return box, ball


def test_train_thickness_net_single_process(tmp_path, cache):
    from torch_ao.thickness import NetThickness

    out = tmp_path / "out"
    box, ball = small_meshes(tmp_path / "meshes")
    proc = run("train_thickness_net.py", "--tiny", "--meshes", box, "--holdout-meshes", ball, "--out", out, cache=cache)
    result = json.loads((out / "result.json").read_text())
    assert result["world_size"] == 1 and result["steps"] == len(result["history"]) > 0
    stages = [h["stage"] for h in result["history"]]
    assert stages[0] == "supervised" and stages[-1] == "end-to-end" and stages == sorted(stages, reverse=True)
    rows = result["holdout"]
    assert {"thickness net", "untrained net (init everywhere)", "true back-face layer",
            "thickness net after stage a (supervised only)"} <= set(rows)
    assert all(finite(r) for r in rows.values()) and any(k.startswith("best scalar") for k in rows)
    assert set(result["holdout_views"]) == {"fence/s1000", "floating/s1000", f"{ball}/s1000"}
    # stage a learns the back-face thickness: the held-out thickness error falls below the constant start's
    err = result["thickness_error"]
    assert err["net after stage a"]["mae"] < 0.8 * err["untrained net"]["mae"]
    assert NetThickness.load(out / "thickness_net_stage_a.pt").scale == 0.5
    model = NetThickness.load(out / "thickness_net.pt")
    assert model.scale == 0.5 and all(torch.isfinite(p).all() for p in model.cnn.parameters())
    assert "held-out views" in proc.stdout and "thickness MAE" in proc.stdout


@pytest.mark.slow
def test_train_thickness_net_resumes_after_sigkill(tmp_path, cache):
    """Kill the training with SIGKILL once a checkpoint exists; the same command finishes it with the
    same weights as an uninterrupted run."""
    common = ["--tiny", "--epochs", "3", "--checkpoint-every", "1", "--no-eval"]
    run("train_thickness_net.py", *common, "--out", tmp_path / "full", cache=cache)
    full = json.loads((tmp_path / "full" / "rank0.json").read_text())

    out = tmp_path / "killed"
    cmd = [sys.executable, str(EXAMPLES / "train_thickness_net.py"), *common, "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env(cache), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (out / "checkpoint.pt").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert 0 < saved["step"] < full["steps"], "the kill should land mid-run"
    assert not (out / "rank0.json").exists()
    resumed = run("train_thickness_net.py", *common, "--out", out, cache=cache)
    assert "resumed from" in resumed.stdout
    again = json.loads((out / "rank0.json").read_text())
    assert again["checksum"] == full["checksum"]


@pytest.mark.slow
def test_train_thickness_net_ddp_two_processes_gloo(tmp_path, cache):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone",
           str(EXAMPLES / "train_thickness_net.py"), "--tiny", "--batch", "3", "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env(cache), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ranks = [json.loads((out / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert [r["rank"] for r in ranks] == [0, 1]
    assert all(r["world_size"] == 2 and r["backend"] == "gloo" for r in ranks)
    assert ranks[0]["steps"] == ranks[1]["steps"] > 0
    assert ranks[0]["views_seen"] != ranks[1]["views_seen"]  # each rank trained on its own shard
    assert ranks[0]["checksum"] == ranks[1]["checksum"]  # identical weights after training
    result = json.loads((out / "result.json").read_text())
    assert result["world_size"] == 2 and result["checksum"] == ranks[0]["checksum"]
    assert (out / "thickness_net.pt").exists() and (out / "checkpoint.pt").exists()
    assert proc.stdout.count("held-out views") == 1  # only rank 0 prints the evaluation

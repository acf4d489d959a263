"""Data-parallel fitting: two CPU processes under ``torchrun`` (gloo) give one process's result, each
reading only its shard of the views; a rank that dies mid-fit leaves a checkpoint that a second
``torchrun`` resumes to the same result; ``torch-ao fit`` under ``torchrun`` writes one process's
params.json. The collectives are also checked without a process group (one process is rank 0 of 1)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torch_ao import distributed

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = Path(__file__).resolve().parent / "fit_ranks.py"


def _env():
    return {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "OMP_NUM_THREADS": "1"}


def _run(*argv, ranks=1, check=True):
    launcher = [sys.executable] if ranks == 1 else [sys.executable, "-m", "torch.distributed.run", "--standalone",
                                                     f"--nproc_per_node={ranks}"]
    proc = subprocess.run([*launcher, *map(str, argv)], cwd=ROOT, env=_env(), capture_output=True, text=True,
                          timeout=600)
    if check:
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _ranks(out, n):
    return [json.loads((out / f"rank{r}.json").read_text()) for r in range(n)]


def _assert_same_fit(got, expected):
    for name, value in expected["parameters"].items():
        assert got["parameters"][name] == pytest.approx(value, rel=1e-5, abs=1e-7), name
    assert got["history"] == pytest.approx(expected["history"], rel=1e-5)
    assert got["hard"] == pytest.approx(expected["hard"], rel=1e-5)
    assert got["best_step"] == expected["best_step"]


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    sys.path.insert(0, str(SCRIPT.parent))
    import fit_ranks

    folder = tmp_path_factory.mktemp("views")
    fit_ranks.write_views(folder)
    out = tmp_path_factory.mktemp("one")
    _run(SCRIPT, folder, out)
    return folder, _ranks(out, 1)[0]


@pytest.mark.slow
def test_two_ranks_give_one_process_result_and_share_the_reads(one_process, tmp_path):
    folder, single = one_process
    _run(SCRIPT, folder, tmp_path, ranks=2)
    ranks = _ranks(tmp_path, 2)
    assert [r["world"] for r in ranks] == [2, 2] and single["world"] == 1
    for r in ranks:
        _assert_same_fit(r, single)
    assert ranks[0]["parameters"] == ranks[1]["parameters"]  # every rank took the same steps, bit for bit
    # each file read once per pass by one rank: the ranks' reads add up to one process's, and each did fewer
    assert ranks[0]["reads"] + ranks[1]["reads"] == single["reads"]
    assert max(r["reads"] for r in ranks) < single["reads"]
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=True)  # written by rank 0 only, whole
    assert saved["state"]["step"] == 9 and not list(tmp_path.glob("*.tmp*"))


@pytest.mark.slow
def test_a_rank_that_dies_mid_fit_leaves_a_checkpoint_that_two_ranks_resume(one_process, tmp_path):
    folder, single = one_process
    crashed = _run(SCRIPT, folder, tmp_path, "--crash-after", 9, ranks=2, check=False)
    assert crashed.returncode != 0 and "crash at forward 9" in crashed.stderr + crashed.stdout
    step = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["state"]["step"]
    assert 0 < step < 9, "the crash should land mid-fit"
    assert not (tmp_path / "rank0.json").exists()
    _run(SCRIPT, folder, tmp_path, ranks=2)
    for r in _ranks(tmp_path, 2):
        _assert_same_fit(r, single)


@pytest.mark.slow
def test_one_process_resumes_a_checkpoint_of_two_ranks(one_process, tmp_path):
    """The checkpoint does not depend on the number of ranks: a one-process run finishes a two-rank fit."""
    folder, single = one_process
    _run(SCRIPT, folder, tmp_path, "--crash-after", 9, ranks=2, check=False)
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=True)["state"]["step"] < 9
    _run(SCRIPT, folder, tmp_path)
    _assert_same_fit(_ranks(tmp_path, 1)[0], single)


def test_without_a_process_group_this_is_rank_0_of_1():
    assert not distributed.is_distributed()
    assert (distributed.rank(), distributed.world_size(), distributed.is_main()) == (0, 1, True)
    values = torch.tensor([1.5, -2.0], dtype=torch.float64)
    assert distributed.sum_over_ranks(values) is values
    assert distributed.gather_objects({"a": 1}) == [{"a": 1}]
    assert distributed.broadcast_object([3]) == [3]
    assert distributed.rank_device("cpu") == torch.device("cpu")
    assert not distributed.init_from_environment("cpu")  # no WORLD_SIZE: nothing started


def test_shards_cover_every_item_once_in_round_robin():
    items = list(range(7))
    parts = [distributed.shard(items, r, 3) for r in range(3)]
    assert parts == [[0, 3, 6], [1, 4], [2, 5]]
    assert sorted(i for p in parts for i in p) == items
    assert distributed.shard(items) == items  # this process: rank 0 of 1

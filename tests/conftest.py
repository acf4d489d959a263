"""Test-session settings."""
import pytest
import torch

# The tests run many small tensor ops (the walk on small frames): one thread is faster than two,
# and it keeps subprocess tests (DDP, kill-and-resume) from oversubscribing a 2-core machine.
torch.set_num_threads(1)


def mesh_scenes_missing(*names: str) -> pytest.MarkDecorator:
    """Skip where the files of built-in mesh scenes (all, or ``names``) are missing: Debian's
    assimp-testmodels, which `.ci/run` installs."""
    from torch_ao.reference import MESH_SCENES, scene_unavailable

    why = next(filter(None, map(scene_unavailable, names or tuple(MESH_SCENES))), None)
    return pytest.mark.skipif(why is not None, reason=why or "")

"""Test-session settings."""
import pytest
import torch

# The tests run many small tensor ops (the walk on small frames): one thread is faster than two,
# and it keeps subprocess tests (DDP, kill-and-resume) from oversubscribing a 2-core machine.
torch.set_num_threads(1)

#: the test files whose tests run longest (NVRTC compiling the CUDA source, the 528 more drawn calls: a minute or two
#: a test)
_FIRST = ("test_kernels_nvrtc.py", "test_kernels_combinations.py")


def pytest_collection_modifyitems(config, items):
    """The longest tests first, so that with pytest-xdist (``-n auto --dist loadgroup``, README) they run beside
    the rest instead of ending the run on one worker alone."""
    items.sort(key=lambda item: item.path.name not in _FIRST)  # (stable: the rest keep their order)


def mesh_scenes_missing(*names: str) -> pytest.MarkDecorator:
    """Skip where the files of built-in mesh scenes (all, or ``names``) are missing: Debian's
    assimp-testmodels, which `.ci/run` installs."""
    from torch_ao.reference import MESH_SCENES, scene_unavailable

    why = next(filter(None, map(scene_unavailable, names or tuple(MESH_SCENES))), None)
    return pytest.mark.skipif(why is not None, reason=why or "")

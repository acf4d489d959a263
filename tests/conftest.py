"""Test-session settings."""
import pytest
import torch

# The tests run many small tensor ops (the walk on small frames): one thread is faster than two,
# and it keeps subprocess tests (DDP, kill-and-resume) from oversubscribing a 2-core machine.
torch.set_num_threads(1)

#: the tests that run longest: NVRTC compiling the CUDA source (a file of them), and the 528 more drawn calls
#: (a test), a minute or two each
_FIRST = ("test_kernels_nvrtc.py", "test_kernel_agrees_with_the_tensor_walk_on_many_more_drawn_options")


def pytest_collection_modifyitems(config, items):
    """The longest tests first, so that with pytest-xdist (``-n auto --dist loadgroup``, README) they run beside
    the rest instead of ending the run on one worker alone."""
    items.sort(key=lambda item: item.path.name not in _FIRST and getattr(item, "originalname", "") not in _FIRST)


def mesh_scenes_missing(*names: str) -> pytest.MarkDecorator:
    """Skip where the files of built-in mesh scenes (all, or ``names``) are missing: Debian's
    assimp-testmodels, which `.ci/run` installs."""
    from torch_ao.reference import MESH_SCENES, scene_unavailable

    why = next(filter(None, map(scene_unavailable, names or tuple(MESH_SCENES))), None)
    return pytest.mark.skipif(why is not None, reason=why or "")

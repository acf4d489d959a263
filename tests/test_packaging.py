"""What an installed (non-editable) torch_ao reads at run time is in its wheel: every source file of the package
that is not Python (the kernels' C++ and CUDA sources, the tracer's C++) matches its package's ``package-data``."""
import fnmatch
import subprocess
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # (Python 3.10: its backport, where installed)
    tomllib = pytest.importorskip("tomli")

ROOT = Path(__file__).resolve().parents[1]


def _package_data() -> dict[str, list[str]]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return config["tool"]["setuptools"]["package-data"]


def _data_files() -> list[Path]:
    """The package's files under version control that are not Python."""
    listed = subprocess.run(["git", "ls-files", "torch_ao"], cwd=ROOT, capture_output=True, text=True, check=True)
    return [ROOT / name for name in listed.stdout.split() if not name.endswith(".py")]


def test_every_non_python_source_is_package_data():
    patterns = _package_data()
    files = _data_files()
    assert any(f.suffix == ".cu" for f in files) and any(f.suffix == ".h" for f in files)
    missing = []
    for path in files:
        package = ".".join(path.parent.relative_to(ROOT).parts)
        if not any(fnmatch.fnmatch(path.name, p) for p in patterns.get(package, [])):
            missing.append(str(path.relative_to(ROOT)))
    assert not missing, f"not in pyproject's package-data (a pip-installed torch_ao would lack them): {missing}"

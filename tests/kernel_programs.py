"""Small C++ programs compiled with the kernels' flags and torch's headers (the lanes and the kernels' headers are
includable on their own), run, and their standard output returned: the tests of what no operator exposes."""
import shutil
import subprocess
from pathlib import Path

import pytest

from torch_ao.kernels import build

COMPILER = shutil.which("g++") or shutil.which("c++")
#: the tests' mark where no C++ compiler is found
needs_compiler = pytest.mark.skipif(COMPILER is None, reason="needs a C++ compiler")


def run_program(source: str, folder: Path, name: str = "program") -> str:
    """Compile ``source`` in ``folder`` as the CPU kernels are compiled (their flags, torch's include and library
    paths, the kernels' folder on the include path), run it and return its standard output; the compiler's errors
    in the assertion's message."""
    from torch.utils import cpp_extension

    (folder / f"{name}.cpp").write_text(source)
    _, flags, _ = build.cpu_build_options()
    includes = [f"-I{p}" for p in cpp_extension.include_paths()] + [f"-I{Path(build.__file__).parent}"]
    libraries = cpp_extension.library_paths()
    command = [COMPILER, "-std=c++17", *flags, *includes, str(folder / f"{name}.cpp"), "-o", str(folder / name),
               *[f"-L{p}" for p in libraries], *[f"-Wl,-rpath,{p}" for p in libraries], "-lc10", "-ltorch_cpu"]
    compiled = subprocess.run(command, capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stderr[-3000:]
    return subprocess.run([str(folder / name)], capture_output=True, text=True, check=True).stdout

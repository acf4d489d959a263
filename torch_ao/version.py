"""The library's version (``torch_ao.__version__``, ``torch-ao --version``, recorded in the files it writes)."""
__version__ = "0.1.0"

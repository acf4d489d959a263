"""Screen-space AO methods, one file per family, all on the shared slice-marching core."""
from __future__ import annotations

import importlib

from .base import PRESETS, AOOutput, ScreenSpaceAO, resolve_preset

#: Method name (CLI and reports) -> (module in this package, class name). Imported on first use.
_REGISTRY: dict[str, tuple[str, str]] = {
    "ssao": ("ssao", "SSAO"),
    "hbao": ("hbao", "HBAO"),
    "ue4_ssao": ("ue4_ssao", "UE4SSAO"),
    "gtao": ("gtao", "GTAO"),
    "pssao": ("pssao", "PSSAO"),
    "bitmask": ("bitmask", "BitmaskAO"),
    "ssilvb": ("bitmask", "SSILVB"),
}


class _Methods(dict):
    """``name -> class``, importing each method's module on first access."""

    def __missing__(self, name: str):
        if name not in _REGISTRY:
            raise KeyError(name)
        module, cls = _REGISTRY[name]
        value = getattr(importlib.import_module(f"{__name__}.{module}"), cls)
        self[name] = value
        return value

    def __contains__(self, name) -> bool:
        return name in _REGISTRY

    def __iter__(self):
        return iter(_REGISTRY)

    def __len__(self) -> int:
        return len(_REGISTRY)

    def keys(self):
        return _REGISTRY.keys()


METHODS = _Methods()


def get_method(name: str) -> type[ScreenSpaceAO]:
    """The module class of method ``name`` (see ``METHODS``); a clear error for unknown names."""
    if name not in _REGISTRY:
        raise ValueError(f"method: unknown method {name!r}; expected one of {', '.join(sorted(_REGISTRY))}")
    return METHODS[name]


__all__ = ["METHODS", "PRESETS", "AOOutput", "ScreenSpaceAO", "get_method", "resolve_preset"]

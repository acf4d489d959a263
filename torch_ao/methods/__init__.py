"""Screen-space AO methods, one file per family, all on the shared walk (:mod:`torch_ao.walk`)."""
from __future__ import annotations

from .base import AOOutput, ScreenSpaceAO
from .bitmask import SSILVB, BitmaskAO
from .common import DEFAULT_PRESET, PRESETS, Sampling, resolve_preset
from .gtao import GTAO
from .hbao import HBAO
from .pssao import PSSAO
from .ssao import SSAO
from .ue4_ssao import UE4SSAO

#: Method name (CLI and reports) -> module class.
METHODS: dict[str, type[ScreenSpaceAO]] = {
    "ssao": SSAO,
    "hbao": HBAO,
    "ue4_ssao": UE4SSAO,
    "gtao": GTAO,
    "pssao": PSSAO,
    "bitmask": BitmaskAO,
    "ssilvb": SSILVB,
}


def get_method(name: str) -> type[ScreenSpaceAO]:
    """The module class of method ``name`` (see ``METHODS``); a clear error for unknown names."""
    if name not in METHODS:
        raise ValueError(f"method: unknown method {name!r}; expected one of {', '.join(sorted(METHODS))}")
    return METHODS[name]


__all__ = ["METHODS", "DEFAULT_PRESET", "PRESETS", "AOOutput", "ScreenSpaceAO", "Sampling", "get_method", "resolve_preset"]

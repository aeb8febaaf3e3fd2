"""cadreg: CAD-aided coarse-to-fine registration of one RGB-D frame to a pre-built indoor map.

Public API (what the service, the clients' tests and the CLI use):
    Frame, CameraIntrinsics           a query frame (cadreg.frame, cadreg.camera)
    Site                              a loaded site bundle: enhanced map, raw map, semantic graph, label map
    Localizer                         Localizer.from_site(site, config).localize(frame) -> LocalizationResult
    LocalizationResult, Status        the answer (cadreg.result)
    errors                            the one error tree (cadreg.errors)
Heavy modules are imported lazily so `import cadreg` stays cheap.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "Frame": "cadreg.frame",
    "CameraIntrinsics": "cadreg.camera",
    "LocalizationResult": "cadreg.result",
    "Status": "cadreg.result",
    "Site": "cadreg.site.bundle",
    "Localizer": "cadreg.localize.localizer",
    "LocalizeConfig": "cadreg.config",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'cadreg' has no attribute {name!r}")


__all__ = list(_LAZY) + ["__version__"]

"""mavvo: visual odometry for drones with known gravity, over MAVLink.

The package is layered; each folder may import only the ones listed below it (``docs/design.md``):

- ``commands/`` and ``cli.py``: the ``mavvo`` command (argument parsing, one module per command);
- ``service/``: the daemon and its edges (MAVLink link, camera sources, timing, recorder, settings);
- ``odometry/``: paired frames in, filtered metric poses out (pure: no threads, sockets or clocks);
- ``estimation/``: robust relative pose (RANSAC, refinement, model selection);
- ``geometry/``: frames, camera models and the paper's solvers (pure numpy);
- ``errors``, ``options`` and ``types`` at the top level: the shared vocabulary every layer may use.

Modules that moved into the folders stay importable under their old flat names (``mavvo.frames``,
``mavvo.relpose``, ...), so code written against earlier versions keeps working.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types

__version__ = "0.1.0"

# Old flat module name -> where it lives now.
_MOVED = {
    "mavvo.camera_model": "mavvo.geometry.camera_model",
    "mavvo.frames": "mavvo.geometry.frames",
    "mavvo.polyroots": "mavvo.geometry.polyroots",
    "mavvo.residuals": "mavvo.geometry.residuals",
    "mavvo.refine": "mavvo.geometry.refine",
    "mavvo.solvers": "mavvo.geometry",
    "mavvo.relpose": "mavvo.estimation.relpose",
    "mavvo.frontend": "mavvo.odometry.frontend",
    "mavvo.keyframes": "mavvo.odometry.keyframes",
    "mavvo.scale": "mavvo.odometry.scale",
    "mavvo.filter": "mavvo.odometry.filter",
    "mavvo.link": "mavvo.service.link",
    "mavvo.timing": "mavvo.service.timing",
    "mavvo.camera": "mavvo.service.camera",
    "mavvo.messages": "mavvo.service.messages",
    "mavvo.recorder": "mavvo.service.recorder",
    "mavvo.tlog": "mavvo.service.tlog",
    "mavvo.daemon": "mavvo.service.daemon",
    "mavvo.settings": "mavvo.service.settings",
    "mavvo.sdnotify": "mavvo.service.sdnotify",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old flat module name to the module that now holds it (the same module object)."""

    def find_spec(self, fullname: str, path: object = None, target: object = None) -> importlib.machinery.ModuleSpec | None:
        return importlib.machinery.ModuleSpec(fullname, self) if fullname in _MOVED else None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        return importlib.import_module(_MOVED[spec.name])

    def exec_module(self, module: types.ModuleType) -> None:
        """Nothing to run: the module was executed under its new name."""


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())

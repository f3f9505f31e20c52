"""Lets a virtual environment import the distribution's PyGObject (``gi``), for the ``gst:`` camera.

GStreamer reaches Python through the distribution's ``python3-gi`` and ``python3-gst-1.0``, which live in
the system's dist-packages; a venv made without ``--system-site-packages`` (``make setup``'s) cannot
import them, and ``--system-site-packages`` would bring every system package along. This links the one
package ``gi`` into the venv (a folder of its own on a ``.pth`` line) when the system has one built for
this interpreter's ABI, and says in one line what it did or what to install. ``make setup`` runs it
with the venv's Python; it changes nothing when ``gi`` already imports.

    .venv/bin/python tools/link_system_gi.py
"""

from __future__ import annotations

import importlib.util
import sys
import sysconfig
from pathlib import Path

SEARCH = (
    "/usr/lib/python3/dist-packages",
    f"/usr/lib/python{sys.version_info.major}.{sys.version_info.minor}/dist-packages",
    f"/usr/local/lib/python{sys.version_info.major}.{sys.version_info.minor}/dist-packages",
)
LINK_DIR = "_mavvo_system_gi"
APT = "apt-get install python3-gi python3-gst-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good"


def system_gi(search: tuple[str, ...] = SEARCH, abi_tag: str = sys.implementation.cache_tag) -> Path | None:
    """The system's ``gi`` package folder whose compiled module fits ``abi_tag`` (``cpython-311``), or None."""
    for folder in search:
        gi = Path(folder) / "gi"
        if any(gi.glob(f"_gi.{abi_tag}-*.so")):
            return gi
    return None


def main() -> int:
    if sys.prefix == sys.base_prefix:
        print("link_system_gi: not in a virtual environment; nothing to do")
        return 0
    if importlib.util.find_spec("gi") is not None:
        print("gst: camera: PyGObject importable")
        return 0
    gi = system_gi()
    if gi is None:
        print(f"gst: camera unavailable (no system PyGObject for {sys.implementation.cache_tag}); for it: sudo {APT}")
        return 0
    site = Path(sysconfig.get_paths()["purelib"])
    link_dir = site / LINK_DIR
    link_dir.mkdir(exist_ok=True)
    link = link_dir / "gi"
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(gi, target_is_directory=True)
    (site / f"{LINK_DIR}.pth").write_text(f"{link_dir}\n", encoding="utf-8")
    print(f"gst: camera: linked the system's PyGObject ({gi}) into the venv")
    return 0


if __name__ == "__main__":
    sys.exit(main())

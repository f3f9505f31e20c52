"""Installing: ``make setup`` notices a virtual environment copied from another place (its scripts
still name the old path) and makes it anew, and leaves one made in place alone."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed here")
def test_make_setup_rebuilds_a_venv_copied_from_elsewhere(tmp_path):
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(ROOT / name, tmp_path / name)
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "pip").write_text("#!/opt/elsewhere/.venv/bin/python\n")
    (tmp_path / ".venv" / ".installed").touch()  # newer than pyproject.toml: up to date but for its place

    def planned() -> str:
        out = subprocess.run(["make", "-n", "setup"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        return out.stdout

    moved = planned()
    assert "rm -rf .venv" in moved and "python3 -m venv .venv" in moved and "pip install" in moved
    (bin_dir / "pip").write_text(f"#!{bin_dir}/python\n")
    (tmp_path / ".venv" / ".installed").touch()
    assert "Nothing to be done" in subprocess.run(["make", "-n", "setup"], cwd=tmp_path, capture_output=True, text=True, timeout=60).stdout

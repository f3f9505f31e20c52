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
    assert (
        "Nothing to be done"
        in subprocess.run(["make", "-n", "setup"], cwd=tmp_path, capture_output=True, text=True, timeout=60).stdout
    )


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed here")
def test_make_install_from_a_copied_checkout_runs(tmp_path):
    """A checkout copied with its .venv (which names another place) installs with a venv made in
    place, a unit pointing at it, and the settings; the installed mavvo runs."""
    src = tmp_path / "checkout"
    shutil.copytree(
        ROOT,
        src,
        ignore=shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info", "mavvo-sim-out", ".hypothesis"),
    )
    (src / ".venv" / "bin").mkdir(parents=True)
    (src / ".venv" / "bin" / "pip").write_text("#!/somewhere/else/.venv/bin/python\n")
    prefix, etc, units, cache = (
        tmp_path / "opt" / "mavvo",
        tmp_path / "etc" / "mavvo",
        tmp_path / "units",
        tmp_path / "cache",
    )
    out = subprocess.run(
        ["make", "install", f"PREFIX={prefix}", f"ETCDIR={etc}", f"UNITDIR={units}", f"CACHEDIR={cache}", "SYSTEM=0"],
        cwd=src,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "installed: edit" in out.stdout and ": ok" in out.stdout
    version = subprocess.run(
        [prefix / ".venv" / "bin" / "mavvo", "--version"], capture_output=True, text=True, timeout=120
    )
    assert version.returncode == 0 and version.stdout.startswith("mavvo ")
    unit = (units / "mavvo.service").read_text()
    assert f"ExecStart={prefix}/.venv/bin/mavvo run --config {etc}/mavvo.yaml" in unit
    assert "=/opt/mavvo" not in unit and " /opt/mavvo" not in unit  # every path of the unit moved to PREFIX
    assert f"NUMBA_CACHE_DIR={cache}/numba" in unit and any((cache / "numba").rglob("*.nbi"))  # the kernels, compiled
    assert (etc / "mavvo.yaml").read_text() == (ROOT / "config" / "default.yaml").read_text()

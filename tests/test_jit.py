"""The compiled kernels: the same source runs as Python (NUMBA_DISABLE_JIT=1) with the same results,
and a warm cache is used as it is (nothing compiled again), a cold one is filled."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# One estimate on each path of the relative pose, printed as JSON: run compiled and as Python.
_SCRIPT = """
import json, numpy as np
from mavvo.estimation.relpose import estimate_upright_relpose
from mavvo.geometry import solve_upright_3pt
from mavvo.sim.world.twoview import add_outliers, make_scene
rng = np.random.default_rng(7)
out = []
for structure in ("volume", "ground"):
    s = make_scene(rng, 120, structure=structure, pixel_noise_px=0.5, imu_noise_rad=0.003)
    s, _ = add_outliers(s, 0.3, rng)
    for sigma in (None, (0.003, 0.003)):
        r = estimate_upright_relpose(s.f1_lvl, s.f2_lvl, max_err_rad=0.002, attitude_sigma_rad=sigma, seed=3)
        out.append([r.model, r.yaw_rad, *r.t_2_1, *r.tilt1_rad, *r.tilt2_rad, int(r.num_inliers)])
E = solve_upright_3pt(s.f1_lvl[:3], s.f2_lvl[:3])
out.append(E.ravel().tolist())
print(json.dumps(out))
"""


def _run(env: dict[str, str]) -> list:
    proc = subprocess.run(
        [sys.executable, "-c", _SCRIPT],
        cwd=ROOT,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_the_kernels_run_as_python_with_the_same_results():
    compiled = _run({})
    python = _run({"NUMBA_DISABLE_JIT": "1"})
    assert len(compiled) == 5 and len(compiled[-1]) >= 9  # four estimates and at least one 3-point solution
    for a, b in zip(compiled[:4], python[:4]):
        assert a[0] == b[0] and a[-1] == b[-1]  # the same model and inlier count
        assert a[1:-1] == pytest.approx(b[1:-1], abs=1e-7)
    assert compiled[-1] == pytest.approx(python[-1], abs=1e-9)


def _cache_files(folder: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*.nb[ic]")}


def _warm(cache: Path | None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    proc = subprocess.run(
        [sys.executable, "-m", "mavvo.estimation.warmup"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0 and "mavvo kernels ready" in proc.stderr, proc.stderr
    # Said before the work, so a first run's minute of compiling is not a silent one.
    assert proc.stderr.splitlines()[0].startswith("mavvo kernels: loading, or compiling"), proc.stderr
    return proc


# A few frames of a simulated flight through the whole odometry (frontend, relative pose, scale).
_FLIGHT = """
from mavvo.odometry.pipeline import Odometry
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.paired_frames import PairedSequence
scenario = load_scenario("survey")
seq = PairedSequence(scenario)
vo = Odometry(scenario.camera.camera_model(), seq.R_body_cam)
estimates = 0
for i, frame in enumerate(seq):
    estimates += vo.step(frame) is not None
    if i == 12:
        break
print(estimates)
"""


def test_a_warm_cache_is_loaded_without_compiling_anything_again():
    """make test warms the cache first; a new process (a service starting) then writes nothing to it: every
    kernel can be cached and is found, and the warm-up reaches every kernel the odometry runs."""
    cache = Path(os.environ["NUMBA_CACHE_DIR"]) if os.environ.get("NUMBA_CACHE_DIR") else ROOT / "mavvo"
    _warm(None)
    before = _cache_files(cache)
    assert len(before) >= 20, "the kernels' cache files"
    _warm(None)
    assert _cache_files(cache) == before
    flight = subprocess.run([sys.executable, "-c", _FLIGHT], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert flight.returncode == 0, flight.stderr
    assert int(flight.stdout) >= 5  # the frames went through the relative pose
    new = sorted(str(p.relative_to(cache)) for p in set(_cache_files(cache)) - set(before))
    assert not new, f"compiled after the warm-up: {new}"


def _sim(cache: Path, out: Path) -> dict:
    """``mavvo sim`` (the service against the simulator, lockstep) on 3 s of the hover with this kernel cache."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    env.pop("NUMBA_DISABLE_JIT", None)
    proc = subprocess.run(
        [sys.executable, "-m", "mavvo", "sim", "--scenario", "hover", "--duration", "3", "--json", "--out", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.slow  # compiles every kernel twice: about two minutes
def test_the_service_starts_with_a_cold_cache_and_with_one_the_warm_up_filled(tmp_path):
    """The daemon warms the kernels before READY=1: started on an empty cache it compiles them into it
    and estimates; on a cache the warm-up alone filled (``make install``) it compiles nothing more,
    read-only arrays included (numba types them apart), and estimates the same (lockstep)."""
    cold = _sim(tmp_path / "cold-cache", tmp_path / "cold")
    assert len(_cache_files(tmp_path / "cold-cache")) >= 20 and cold["estimates_received"] > 10
    cache = tmp_path / "cache"
    _warm(cache)
    warmed = _cache_files(cache)
    warm = _sim(cache, tmp_path / "warm")
    new = sorted(str(p.relative_to(cache)) for p in set(_cache_files(cache)) - set(warmed))
    assert not new, f"the service compiled what the warm-up did not: {new}"
    assert warm["estimates_received"] == cold["estimates_received"] and warm["ate_rmse_m"] == cold["ate_rmse_m"]


# Two modules of kernels, the second calling the first (numba compiles the callee into the caller).
_CALLEE = "from mavvo.jit import kernel\n\n@kernel\ndef value():\n    return {}\n"
_CALLER = "from mavvo.jit import kernel\nfrom callee import value\n\n@kernel\ndef twice():\n    return 2 * value()\n"
_MAIN = "import sys\nfrom mavvo.jit import refresh_cache\nimport caller\nif sys.argv[1] == 'refresh':\n    refresh_cache()\nprint(caller.twice())\n"


def _twice(folder: Path, refresh: bool) -> int:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(folder), str(ROOT)]),
        "NUMBA_CACHE_DIR": str(folder / "cache"),
    }
    env.pop("NUMBA_DISABLE_JIT", None)
    proc = subprocess.run(
        [sys.executable, str(folder / "main.py"), "refresh" if refresh else "plain"],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return int(proc.stdout)


def test_a_kernel_is_compiled_again_when_a_kernel_it_calls_changed_in_another_file(tmp_path):
    (tmp_path / "caller.py").write_text(_CALLER)
    (tmp_path / "main.py").write_text(_MAIN)
    (tmp_path / "callee.py").write_text(_CALLEE.format(1))
    assert _twice(tmp_path, refresh=True) == 2  # compiled and cached
    (tmp_path / "callee.py").write_text(_CALLEE.format(50))  # another size: no stale .pyc within the same second
    # numba alone would load the caller with the old callee compiled in...
    assert _twice(tmp_path, refresh=False) == 2
    # ... the stamp of the sources sees the change and empties the cache first.
    assert _twice(tmp_path, refresh=True) == 100
    assert _twice(tmp_path, refresh=True) == 100  # and the new one is cached in turn

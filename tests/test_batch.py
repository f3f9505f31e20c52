"""``mavvo batch`` on a real Dask cluster of local processes: its rows equal the sequential replays bit
for bit, a broken flight or a dying worker costs one row, a second run resumes, and a scheduler and
worker started as their own processes on 127.0.0.1 are reached with --scheduler."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed", reason="the fleet extra (make setup installs it)")

from mavvo.cli import main  # noqa: E402
from mavvo.fleet.batch import (  # noqa: E402
    BatchTask,
    Flight,
    Journal,
    Settings,
    expand_flights,
    expand_settings,
    make_tasks,
    replay_task,
)
from mavvo.fleet.engine import run_tasks  # noqa: E402
from mavvo.service.recorder import RecordOptions  # noqa: E402
from mavvo.service.settings import ServiceConfig  # noqa: E402
from mavvo.sim.scenarios.loader import load_scenario  # noqa: E402
from mavvo.sim.scenarios.service_run import run_daemon_in_sim  # noqa: E402


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> Path:
    """Two short recorded flights in one folder, and a grid of two settings."""
    root = tmp_path_factory.mktemp("flights")
    for name in ("hover", "figure_eight"):
        run_daemon_in_sim(
            load_scenario(name), ServiceConfig(record=RecordOptions(dir=str(root / "recordings"))), duration_s=6.0
        )
    (root / "grid.yaml").write_text("odometry.filter.accel_sigma_m_s2: [1.0, 6.0]\n")
    return root


def _batch(*args: object) -> int:
    return main(["batch", *map(str, args)])


def test_a_local_cluster_gives_the_sequential_replays_bit_for_bit_and_a_second_run_resumes(flights, tmp_path, capsys):
    out = tmp_path / "out"
    code = _batch(flights / "recordings" / "*", "--grid", flights / "grid.yaml", "--out", out, "--workers", 2)
    assert code == 0, capsys.readouterr().err
    rows = json.loads((out / "results.json").read_text())
    assert len(rows) == 4 and all(r["status"] == "ok" for r in rows)
    # The same tasks replayed one after another in this process: the same estimates, byte for byte.
    tasks = make_tasks(expand_flights([str(flights / "recordings" / "*")]), expand_settings([], flights / "grid.yaml"))
    by_key = {r["key"]: r for r in rows}
    for task in (tasks[0], tasks[-1]):  # one of each flight and of each setting
        assert replay_task(task)["estimates_sha256"] == by_key[task.key]["estimates_sha256"], task
    # Different settings gave different estimates (so the comparison above can fail).
    assert len({r["estimates_sha256"] for r in rows}) > 2
    summary = json.loads((out / "summary.json").read_text())
    assert {s["settings"] for s in summary["settings"]} == {
        "odometry.filter.accel_sigma_m_s2=1",
        "odometry.filter.accel_sigma_m_s2=6",
    }
    assert summary["best"]["settings"] in {s["settings"] for s in summary["settings"]}
    assert all(s["flights_ok"] == 2 and s["end_error_m_median"] is not None for s in summary["settings"])
    assert (out / "batch.png").stat().st_size > 0 and (out / "results.csv").read_text().startswith("key,flight")
    # Again: nothing runs, the journal is unchanged.
    journal = (out / "results.jsonl").read_text()
    capsys.readouterr()
    assert _batch(flights / "recordings" / "*", "--grid", flights / "grid.yaml", "--out", out) == 0
    assert "4 finished before, 0 to run" in capsys.readouterr().err
    assert (out / "results.jsonl").read_text() == journal


def test_a_flight_that_cannot_be_read_is_one_failed_row(flights, tmp_path, capsys):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "meta.json").write_text("{not json")
    (broken / "config.yaml").write_text("{}\n")
    out = tmp_path / "out"
    one = sorted((flights / "recordings").iterdir())[0]
    assert _batch(one, broken, "--out", out, "--workers", 2) == 1
    rows = {Path(r["flight"]).name: r for r in Journal(out).rows()}
    assert rows[one.name]["status"] == "ok"
    assert rows["broken"]["status"] == "failed" and "meta.json: cannot read" in rows["broken"]["reason"]
    assert "\n" not in rows["broken"]["reason"]


def test_bad_settings_are_refused_before_anything_runs(flights, tmp_path, capsys):
    grid = tmp_path / "grid.yaml"
    grid.write_text("odometry.no_such_key: [1, 2]\n")
    assert _batch(flights / "recordings" / "*", "--grid", grid, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert "no_such_key" in err and not (tmp_path / "out" / "results.jsonl").exists()
    assert _batch(tmp_path / "nowhere", "--out", tmp_path / "out") == 2
    assert "nowhere: no such flight" in capsys.readouterr().err


@pytest.mark.slow  # a sweep interrupted and resumed: make soak
def test_ctrl_c_cancels_the_rest_keeps_what_finished_and_the_same_command_resumes(flights, tmp_path, capsys):
    import signal

    out = tmp_path / "out"
    args = ["batch", str(flights / "recordings" / "*"), "--grid", str(flights / "grid.yaml"), "--out", str(out),
            "--workers", "1"]  # fmt: skip
    # Started as a terminal starts its foreground job: SIGINT at its default. A test run started in the
    # background of a non-interactive shell (`make soak &`) ignores SIGINT, and a child inherits that.
    at_a_terminal = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from mavvo.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    proc = subprocess.Popen([sys.executable, "-c", at_a_terminal, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    journal = out / "results.jsonl"
    deadline = time.monotonic() + 120
    while not (journal.exists() and journal.read_text().count("\n") >= 1):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    done = journal.read_text().count("\n")
    assert proc.returncode == 130 and 1 <= done < 4, (proc.returncode, done, err)
    assert "run the same command again to resume" in err and "Traceback" not in err
    assert _batch(*args[1:]) == 0
    assert f"{done} finished before, {4 - done} to run" in capsys.readouterr().err
    assert len(Journal(out).rows()) == 4


# ------------------------------------------------------------------ the engine alone


def die_once(marker: str) -> int:
    """A task whose worker process dies the first time it runs (a killed worker, an out-of-memory kill)."""
    path = Path(marker)
    if not path.exists():
        path.write_text("died")
        os._exit(9)
    return os.getpid()


def die_always(_: object) -> int:
    os._exit(9)


def test_a_task_whose_worker_dies_is_retried_elsewhere_then_marked_failed(tmp_path):
    outcomes = []
    (tmp_path / "lived").write_text("")  # this one does not die
    status = run_tasks(
        die_once, [("once", str(tmp_path / "marker")), ("ok", str(tmp_path / "lived"))], outcomes.append, workers=2
    )
    by_key = {o.key: o for o in outcomes}
    assert status.finished == 2 and status.failed == 0 and by_key["once"].error is None
    outcomes.clear()
    status = run_tasks(die_always, [("dies", None)], outcomes.append, workers=2)
    assert status.failed == 1 and "worker died" in outcomes[0].error


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_running_scheduler_and_worker_are_reached_with_scheduler(flights, tmp_path, capsys):
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--no-dashboard",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
    ]
    try:
        deadline = time.monotonic() + 60
        while True:  # the scheduler is up once its port takes connections
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "the scheduler did not start"
                time.sleep(0.2)
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "distributed.cli.dask_worker",
                    address,
                    "--nthreads",
                    "1",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env=env,
            )
        )
        one = sorted((flights / "recordings").iterdir())[0]
        out = tmp_path / "out"
        assert _batch(one, "--scheduler", address, "--out", out) == 0, capsys.readouterr().err
        [row] = Journal(out).rows()
        task = BatchTask(Flight(str(one.resolve())), Settings("own"))
        assert row["key"] == task.key and row["status"] == "ok"
        assert row["estimates_sha256"] == replay_task(task)["estimates_sha256"]
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(30)


def test_without_dask_the_user_is_told_what_to_install(flights, tmp_path, monkeypatch, capsys):
    """An installed copy has no fleet extra: a clear line and exit 2, not an ImportError's text."""
    monkeypatch.setitem(sys.modules, "distributed", None)
    monkeypatch.setitem(sys.modules, "dask", None)
    assert _batch(flights / "recordings" / "*", "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert "mavvo batch needs Dask: pip install 'mavvo[fleet]'" in err and "Traceback" not in err

"""Ensembles through the Dask execution layer: worker count, failures, lost workers, resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import SMALL_SCENARIO, run_cli

from chipstack.pipeline.execution import Executor


def _scenario(tmp_path: Path, chips: int = 24) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENARIO.replace("chips = 24", f"chips = {chips}"))
    return path


def square_or_fail(x: int) -> int:
    """A task for the executor test: fails for 3."""
    if x == 3:
        raise ValueError("three is not allowed")
    return x * x


def test_results_do_not_depend_on_the_number_of_workers(tmp_path):
    scenario = _scenario(tmp_path)
    outputs = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        result = run_cli(
            "run",
            str(scenario),
            "--to",
            "geometry",
            "--repeats",
            "4",
            "--seed",
            "5",
            "--workers",
            str(workers),
            "--out",
            str(out),
            "--quiet",
        )
        assert result.returncode == 0, result.stderr
        assert json.loads((out / "manifest.json").read_text())["workers"] == workers
        outputs[workers] = out
    one, two = (json.loads((outputs[w] / "ensemble.json").read_text()) for w in (1, 2))
    assert one["descriptors"] == two["descriptors"] and one["seeds"] == two["seeds"]
    for k in range(4):
        poses = f"repeat_{k}/packing/poses_after_batch_02.csv"
        assert (outputs[1] / poses).read_bytes() == (outputs[2] / poses).read_bytes()


def test_a_failing_run_is_reported_and_the_others_complete():
    results, errors = {}, {}
    with Executor(workers=2) as executor:
        executor.run(
            square_or_fail,
            [(k,) for k in range(6)],
            lambda k, value: results.__setitem__(k, value),
            lambda k, error: errors.__setitem__(k, error),
        )
    assert results == {0: 0, 1: 1, 2: 4, 4: 16, 5: 25}
    assert list(errors) == [3] and "three is not allowed" in str(errors[3])


def test_an_unreachable_scheduler_is_one_line_within_ten_seconds(tmp_path):
    start = time.perf_counter()
    result = run_cli(
        "run",
        str(_scenario(tmp_path)),
        "--to",
        "geometry",
        "--repeats",
        "2",
        "--scheduler",
        "tcp://127.0.0.1:9",
        "--out",
        str(tmp_path / "out"),
    )
    assert time.perf_counter() - start < 10
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "tcp://127.0.0.1:9" in lines[0], result.stderr
    assert not (tmp_path / "out").exists()


def test_a_scheduler_that_never_answers_is_one_line_within_ten_seconds(tmp_path):
    import socket

    with socket.socket() as listener:  # accepts connections, never speaks Dask
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        start = time.perf_counter()
        result = run_cli(
            "run",
            str(_scenario(tmp_path)),
            "--to",
            "packing",
            "--repeats",
            "2",
            "--scheduler",
            address,
            "--out",
            str(tmp_path / "out"),
        )
        assert time.perf_counter() - start < 10
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0], result.stderr
    assert not (tmp_path / "out").exists()


def test_overwrite_keeps_the_old_ensemble_until_a_new_run_is_written(tmp_path):
    scenario = str(_scenario(tmp_path))
    out = tmp_path / "ens"
    args = [
        "run",
        scenario,
        "--to",
        "packing",
        "--repeats",
        "2",
        "--workers",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    assert run_cli(*args).returncode == 0
    before = (out / "manifest.json").read_bytes()
    refused = run_cli(*args)
    assert refused.returncode == 2 and "--overwrite" in refused.stderr
    failed = run_cli(*args[:-1], "--overwrite", "--scheduler", "tcp://127.0.0.1:9")
    assert failed.returncode == 2
    assert (out / "manifest.json").read_bytes() == before


def test_bad_worker_flags_are_refused(tmp_path):
    scenario = str(_scenario(tmp_path))
    for args, word in (
        (["--repeats", "2", "--workers", "0"], "--workers"),
        (["--workers", "2"], "only with --repeats"),
        (["--repeats", "2", "--workers", "2", "--scheduler", "tcp://127.0.0.1:9"], "--workers"),
    ):
        result = run_cli("run", scenario, "--out", str(tmp_path / "o"), *args)
        assert result.returncode == 2 and word in result.stderr, result.stderr
    assert not (tmp_path / "o").exists()


def _wait_for(predicate, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _finished(out: Path) -> list[str]:
    return sorted(p.parent.name for p in out.glob("repeat_*/manifest.json"))


def test_an_interrupted_ensemble_resumes_where_it_stopped(tmp_path):
    scenario = str(_scenario(tmp_path))
    out = tmp_path / "ens"
    args = [
        sys.executable,
        "-m",
        "chipstack.pipeline",
        "run",
        scenario,
        "--to",
        "geometry",
        "--repeats",
        "8",
        "--workers",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _wait_for(lambda: len(_finished(out)) >= 2, 120, "two finished runs")
    process.kill()
    process.wait()
    kept = {name: (out / name / "manifest.json").read_bytes() for name in _finished(out)}
    assert 2 <= len(kept) < 8 and (out / "ensemble-state.json").is_file()
    result = run_cli(
        "run", scenario, "--to", "geometry", "--repeats", "8", "--workers", "1", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    resumed = json.loads((out / "manifest.json").read_text())["resumed_runs"]
    assert f"resumed: {len(resumed)} runs" in result.stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["runs"]) == 8 and len(manifest["resumed_runs"]) >= len(kept)
    for name, content in kept.items():
        assert (out / name / "manifest.json").read_bytes() == content  # not recomputed
    assert not (out / "ensemble-state.json").exists()
    assert json.loads((out / "ensemble.json").read_text())["repeats"] == 8


def test_the_ensemble_survives_a_killed_worker(tmp_path):
    """A real scheduler and two real workers on loopback; one worker is killed mid-run."""
    dask = Path(sys.executable).with_name("dask")
    scheduler_file = tmp_path / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    processes = [
        subprocess.Popen(
            [
                str(dask),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(scheduler_file),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
    ]
    try:
        _wait_for(scheduler_file.is_file, 30, "the scheduler")
        address = json.loads(scheduler_file.read_text())["address"]
        for _ in range(2):
            processes.append(
                subprocess.Popen(
                    [
                        str(dask),
                        "worker",
                        address,
                        "--nthreads",
                        "1",
                        "--no-nanny",
                        "--no-dashboard",
                        "--host",
                        "127.0.0.1",
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    env=env,
                    cwd=Path(__file__).parents[1],
                )
            )
        out = tmp_path / "ens"
        ensemble = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "chipstack.pipeline",
                "run",
                str(_scenario(tmp_path, 36)),
                "--to",
                "geometry",
                "--repeats",
                "8",
                "--scheduler",
                address,
                "--out",
                str(out),
                "--quiet",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        _wait_for(lambda: len(_finished(out)) >= 1, 120, "a first finished run")
        processes[1].send_signal(signal.SIGKILL)  # one worker dies mid-ensemble
        stdout, stderr = ensemble.communicate(timeout=300)
        assert ensemble.returncode == 0, stderr
        manifest = json.loads((out / "manifest.json").read_text())
        assert len(manifest["runs"]) == 8 and manifest["failed_runs"] == []
        assert len(_finished(out)) == 8
    finally:
        for process in processes:
            process.kill()
            process.wait()

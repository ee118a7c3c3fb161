"""Issues 21 and 25: one executor, and clean fault paths of the long commands.

Signals are sent to a child process (its own session, so a Ctrl-C reaches its whole process group as
a terminal's would); limits (memory, file size) are set with ``resource.setrlimit`` in a child.
Each test fails on the code before these issues (the comment at its top says what happened then).
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mmslam.cli import main

MMSLAM = [sys.executable, "-m", "mmslam"]
SMALL = ["--source", "analytic", "--variants", "baseline", "--particles", "3", "--steps", "8", "--quiet"]


def _one_line(stderr: str, prefix: str, *needles: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(prefix), stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    assert "Traceback" not in stderr
    return lines[0]


def _tree(p: Path) -> dict[str, bytes]:
    return {str(f.relative_to(p)): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


@pytest.fixture(scope="module")
def ablation(tmp_path_factory) -> Path:
    """A finished 3-seed baseline ablation (8 steps, 3 particles) to copy."""
    out = tmp_path_factory.mktemp("faults") / "abl"
    assert main(["ablate", "paper", "--mc", "3", "--workers", "1", "--out", str(out)] + SMALL) == 0
    return out


def _copy(ablation: Path, tmp_path: Path) -> Path:
    out = tmp_path / "abl"
    shutil.copytree(ablation, out, symlinks=True)
    return out


# ============================================================ issue 21: one executor, the address checked at once
def test_trace_with_a_nonsense_scheduler_is_one_line_before_any_work(tmp_path):
    # before: `trace --executor dask --scheduler nonsense` tried to connect for 10 s (23 s in all), then
    # printed its error and a Client.__del__ traceback
    out = tmp_path / "X"
    r = subprocess.run(MMSLAM + ["trace", "paper", "--source", "analytic", "--executor", "dask", "--scheduler",
                                 "nonsense", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    _one_line(r.stderr, "error: ", "--scheduler 'nonsense'", "tcp://host:8786")
    assert not out.exists()


@pytest.mark.parametrize("argv, needle", [
    (["trace", "paper", "--source", "analytic", "--executor", "dask", "--workers", "5000"], "--workers 5000"),
    (["ablate", "paper", "--source", "analytic", "--executor", "dask", "--workers", "5000"], "--workers 5000"),
    (["trace", "paper", "--source", "analytic", "--executor", "dask", "--scheduler", "tcp://h:0"], "--scheduler"),
    (["ablate", "paper", "--source", "analytic", "--executor", "dask", "--scheduler", "tcp://h:0"], "--scheduler"),
])
def test_trace_and_ablate_check_executor_options_alike(tmp_path, capsys, argv, needle):
    # before: trace accepted --workers 5000 (a LocalCluster of 5000 processes) and any address
    out = tmp_path / "o"
    assert main(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    _one_line(err, "error: ", needle)
    assert not out.exists()


def test_one_executor_module_serves_trace_and_ablate():
    import mmslam.executor as E
    from mmslam.pipelines.ablate import executors as AE
    from mmslam.raytrace import trace as T

    assert AE.check_dask_address is E.check_dask_address and AE._local_pool is E.local_pool
    with pytest.raises(E.ConfigError, match="--scheduler"):
        T.DaskExecutor({"name": "analytic", "max_depth": 1, "samples": 1, "seed": 0}, scheduler="nonsense")
    assert E.pool_size(None, 1) == 1 and E.pool_size(8, 3) == 3 and E.pool_size(2, 10) == 2


# ============================================================ 4. a non-finite job value never vanishes
def _poison(job: Path, table: str, column: str, row: int) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    t = pq.read_table(job / f"{table}.parquet")
    col = t.column(column).to_numpy().astype(float).copy()
    col[row] = np.nan
    pq.write_table(t.set_column(t.column_names.index(column), column, pa.array(col)), job / f"{table}.parquet")


def test_nan_in_stored_jobs_fails_the_report_naming_the_job(ablation, tmp_path, capsys):
    # before: `mmslam report` exited 0, said "runs 3", and the NaN runs silently left the mean and its CI
    from mmslam.errors import CacheError
    from mmslam.pipelines.ablate import aggregate

    out = _copy(ablation, tmp_path)
    before = _tree(out)
    _poison(out / "jobs" / "baseline-seed1", "metrics", "gospa", 40)
    _poison(out / "jobs" / "baseline-seed2", "vehicles", "pos_err", 3)
    assert main(["report", str(out)]) == 2
    _one_line(capsys.readouterr().err, "error: ", "baseline-seed1", "non-finite", "metrics.gospa", "delete")
    assert (out / "summary.json").read_bytes() == before["summary.json"]  # the old summary is not replaced
    shutil.rmtree(out / "jobs" / "baseline-seed1")
    with pytest.raises(CacheError, match=r"baseline-seed2.*vehicles\.pos_err"):
        aggregate(out)


def test_a_fresh_job_with_a_nan_fails_and_is_not_stored(ablation, tmp_path):
    # before: a result with NaN was stored and then averaged over the finite values only
    import concurrent.futures as cf

    from mmslam.errors import MmslamError
    from mmslam.executor import Pool
    from mmslam.pipelines.ablate import Job
    from mmslam.pipelines.ablate.jobs import _drive
    from mmslam.slam.filter.result import Result

    res = Result.load(ablation / "jobs" / "baseline-seed0")
    res.metrics["loc"] = np.asarray(res.metrics["loc"], float).copy()
    res.metrics["loc"][7] = np.inf

    def submit(fn, *args, key=None):
        f = cf.Future()
        f.set_result(res)
        return f

    pool = Pool(submit, lambda fs: iter(fs), lambda fs: None, 1, "fake")
    out = tmp_path / "abl"
    with pytest.raises(MmslamError, match=r"job baseline-seed5: 1 non-finite value in metrics\.loc") as info:
        _drive(pool, [Job("baseline", 5)], out, "unused", 3, None, False, 0, 1)
    assert info.value.exit_code == 1 and not (out / "jobs" / "baseline-seed5").exists()


# ============================================================ 6. Ctrl-C while the workers start
def _children(pid: int) -> list[tuple[int, str]]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            out.append((int(d.name), cmd))
    return out


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="needs /proc")
@pytest.mark.parametrize("delay", [0.2, 0.6])
def test_ctrl_c_while_workers_start_is_one_line_and_no_worker_traceback(ablation, tmp_path, delay):
    # before: a Ctrl-C to the process group in the first seconds: the `interrupted:` line, then worker
    # KeyboardInterrupt tracebacks (the workers ignored SIGINT only once their imports were done)
    out = _copy(ablation, tmp_path)
    shutil.rmtree(out / "jobs")
    (out / "summary.json").unlink()
    argv = MMSLAM + ["ablate", "paper", "--mc", "3", "--workers", "2", "--out", str(out)] + SMALL
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not any("multiprocessing" in c for _, c in _children(proc.pid)):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no worker process started"
            time.sleep(0.01)
        time.sleep(delay)
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, stderr
    _one_line(stderr, "interrupted: ", "re-run the same command")
    assert "KeyboardInterrupt" not in stderr and "InvalidStateError" not in stderr


# ============================================================ 7. SIGTERM like Ctrl-C; a late Ctrl-C
_SIGNAL_DURING_WORK = """
import os, signal, sys, time
import mmslam.scenes.scenario as scenario_mod
def load(*a, **k):
    os.kill(os.getpid(), signal.{sig})
    time.sleep(30)
scenario_mod.load_preset = load
from mmslam.cli import main
sys.exit(main(["scene", "show", "paper", "--out", sys.argv[1]]))
"""


@pytest.mark.parametrize("sig, code, word", [("SIGTERM", 143, "terminated: "), ("SIGINT", 130, "interrupted: ")])
def test_sigterm_is_handled_like_ctrl_c(tmp_path, sig, code, word):
    # before: SIGTERM killed the process: exit -15, no message, nothing kept or said
    r = subprocess.run([sys.executable, "-c", _SIGNAL_DURING_WORK.format(sig=sig), str(tmp_path / "f.png")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == code, r.stderr
    _one_line(r.stderr, word, "re-run the same command")


_SIGNAL_AFTER_WORK = """
import os, signal, sys, time
sys.argv = ["mmslam", "--version"]
from mmslam.cli import main
rc = main()
os.kill(os.getpid(), signal.{sig})  # the run has ended; the process is on its way out
time.sleep(5)
sys.exit(rc)
"""


@pytest.mark.parametrize("sig, code, word", [("SIGINT", 130, "interrupted: "), ("SIGTERM", 143, "terminated: ")])
def test_a_signal_as_the_run_ends_still_gives_the_message_and_code(sig, code, word):
    # before: a Ctrl-C after main() returned: a KeyboardInterrupt traceback and exit -2 (SIGTERM: -15)
    r = subprocess.run([sys.executable, "-c", _SIGNAL_AFTER_WORK.format(sig=sig)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == code, (r.returncode, r.stderr)
    assert r.stdout.startswith("mmslam ")
    _one_line(r.stderr, word)


@pytest.mark.slow
def test_sigterm_to_an_ablation_keeps_finished_jobs_and_resumes(tmp_path):
    # before: SIGTERM killed the ablation (exit -15, no message; the jobs in flight were lost silently)
    out = tmp_path / "abl"
    argv = MMSLAM + ["ablate", "paper", "--mc", "6", "--workers", "1", "--out", str(out)] + SMALL
    argv[argv.index("--particles") + 1] = "40"
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not any((out / "jobs").glob("*/meta.json")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    line = _one_line(stderr, "terminated: ", "re-run the same command")
    kept = len(list((out / "jobs").glob("*/meta.json")))
    assert re.search(rf"\b{kept} of 6 jobs are kept", line), (line, kept)
    done = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"{6 - kept} run, {kept} reused" in done.stdout


# ============================================================ 8. environment failures: one line, exit 2
def _limited(limit: str, value: int, argv: list[str]) -> subprocess.CompletedProcess:
    code = (f"import resource, sys; resource.setrlimit(resource.{limit}, ({value}, {value})); "
            "from mmslam.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", code] + argv, capture_output=True, text=True, timeout=600)


def test_out_of_memory_is_an_environment_failure_not_a_bug(ablation, tmp_path):
    # before: `slam --particles 100000` under `ulimit -v 2000000`: exit 1, "this is a bug". The limit here is
    # 1.5 GB of address space: with the lowest allowed numpy/numba (make test-min) the run fits in 2 GB
    (cache,) = (ablation / "cache").glob("*/manifest.json")
    r = _limited("RLIMIT_AS", 1_500_000 * 1024, ["slam", str(cache.parent), "--particles", "100000", "--steps", "3",
                                                "--out", str(tmp_path / "res")])
    assert r.returncode == 2, r.stderr
    _one_line(r.stderr, "error: out of memory", "MemoryError", "--particles", "re-run")
    assert not (tmp_path / "res").exists()


def test_environment_failure_classification():
    from concurrent.futures.process import BrokenProcessPool

    from mmslam.errors import environment_cause, environment_failure

    assert environment_cause(MemoryError("Unable to allocate 7 GiB")).startswith("out of memory")
    assert "worker process died" in environment_cause(BrokenProcessPool("terminated abruptly"))
    try:
        try:
            raise MemoryError()
        except MemoryError as e:
            raise RuntimeError("numba: allocation failed") from e
    except RuntimeError as wrapped:
        assert environment_cause(wrapped).startswith("out of memory")
    assert environment_cause(ValueError("a real bug")) is None and environment_failure(KeyError("x")) is None


def test_out_of_memory_in_a_worker_keeps_finished_jobs_and_says_so(ablation, tmp_path):
    # before: a worker's MemoryError ended the ablation with "this is a bug" (exit 1), nothing said of the kept jobs
    import concurrent.futures as cf

    from mmslam.errors import EnvironmentFailure
    from mmslam.executor import Pool
    from mmslam.pipelines.ablate import Job
    from mmslam.pipelines.ablate.jobs import _drive
    from mmslam.slam.filter.result import Result

    res = Result.load(ablation / "jobs" / "baseline-seed0")

    def submit(fn, *args, key=None):
        f = cf.Future()
        if key.endswith("seed0"):
            f.set_result(res)
        else:
            f.set_exception(MemoryError("Unable to allocate 7.45 GiB"))
        return f

    out = tmp_path / "abl"
    pool = Pool(submit, lambda fs: iter(fs), lambda fs: None, 1, "fake")
    with pytest.raises(EnvironmentFailure) as info:
        _drive(pool, [Job("baseline", 0), Job("baseline", 1)], out, "unused", 3, None, False, 4, 6)
    msg = str(info.value)
    assert msg.startswith("out of memory (MemoryError: Unable to allocate 7.45 GiB)") and info.value.exit_code == 2
    assert "5 of 6 jobs are kept" in msg and "--workers" in msg and "re-run the same command" in msg
    assert (out / "jobs" / "baseline-seed0" / "meta.json").is_file()


@pytest.mark.slow
def test_losing_the_dask_scheduler_mid_ablation_is_one_line_and_resumes(tmp_path):
    # before: exit 1 "this is a bug" and 26 lines of distributed tracebacks (the finished jobs were kept)
    import socket

    pytest.importorskip("distributed")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    addr = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True}
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port",
                              str(port), "--no-dashboard"], **quiet)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1",
                               "--no-dashboard"], **quiet)
    out = tmp_path / "abl"
    argv = MMSLAM + ["ablate", "paper", "--mc", "6", "--executor", "dask", "--scheduler", addr, "--out", str(out)]
    argv += SMALL
    argv[argv.index("--particles") + 1] = "40"
    try:
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 300
        while not any((out / "jobs").glob("*/meta.json")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        os.killpg(sched.pid, signal.SIGKILL)
        _, stderr = proc.communicate(timeout=180)
    finally:
        for p in (sched, worker):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert proc.returncode == 2, stderr
    line = _one_line(stderr, "error: lost the Dask scheduler", "jobs are kept", "re-run the same command")
    kept = len(list((out / "jobs").glob("*/meta.json")))
    assert re.search(rf"\b{kept} of 6 jobs are kept", line), (line, kept)
    local = [a for a in argv if a not in ("--executor", "dask", "--scheduler", addr)]
    done = subprocess.run(local, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and f"{6 - kept} run, {kept} reused" in done.stdout, done.stderr


# ============================================================ 9. temp files, --set before any work
def test_truncated_summary_temp_is_removed_and_stale_ones_cleaned(ablation, tmp_path):
    # before: under a file-size limit the ablation left a truncated .summary.json.<pid>.tmp that even a
    # successful re-run never removed
    out = _copy(ablation, tmp_path)
    argv = ["ablate", "paper", "--mc", "3", "--workers", "1", "--out", str(out)] + SMALL
    limit = (out / "summary.json").stat().st_size // 2
    assert (out / "ablation.json").stat().st_size < limit and (out / "summary.parquet").stat().st_size < limit
    r = _limited("RLIMIT_FSIZE", limit, argv)
    assert r.returncode == 2 and "File too large" in r.stderr, r.stderr
    assert not list(out.glob(".summary.*.tmp"))  # removed on the failed write
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        stale = out / f".summary.json.{dead}.tmp"  # left by a `kill -9`
        stale.write_text("{trunc")
        others = [out / f".summary.json.{live.pid}.tmp", out / ".summary.json.backup", out / "summary.json.1.tmp",
                  out / f".notes.json.{dead}.tmp"]
        for f in others:
            f.write_text("user")
        assert main(argv) == 0
        assert not stale.exists()
        assert all(f.read_text() == "user" for f in others)  # a live writer's and foreign files stay
    finally:
        live.kill()
        live.wait()


def test_bad_set_value_is_refused_before_the_trace(tmp_path, capsys):
    # before: with --particles given, the cache was traced (out/cache written) before the --set error
    out = tmp_path / "abl"
    assert main(["ablate", "paper", "--mc", "1", "--set", "filter.merge=-5", "--out", str(out)] + SMALL) == 2
    _one_line(capsys.readouterr().err, "error: ", "filter.merge")
    assert not out.exists()
    assert main(["ablate", "paper", "--mc", "1", "--grid", "filter.merge=1,-5", "--out", str(out)] + SMALL) == 2
    _one_line(capsys.readouterr().err, "error: ", "filter.merge")
    assert not out.exists()


def test_lock_conflict_does_not_hide_a_bad_set(ablation, tmp_path, capsys):
    # before: "another ablation (pid N) is writing here" hid the real --set error
    from mmslam.outputs import lock_path

    out = _copy(ablation, tmp_path)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        lock_path(out).write_text(f"{live.pid}\n")
        assert main(["ablate", "paper", "--mc", "3", "--set", "filter.merge=-5", "--out", str(out)] + SMALL) == 2
        err = _one_line(capsys.readouterr().err, "error: ", "filter.merge")
        assert "another" not in err
    finally:
        live.kill()
        live.wait()


def test_out_of_memory_during_a_trace_says_how_many_steps_are_kept(tmp_path):
    # before: a MemoryError in the source ended the trace as "this is a bug" (exit 1)
    from mmslam.errors import EnvironmentFailure
    from mmslam.raytrace.cache import read_manifest
    from mmslam.raytrace.trace import make_source, trace_scenario
    from mmslam.scenes.scenario import load_preset

    scn = load_preset("paper")
    src = make_source("analytic", scn)
    real = src.trace_tables

    def trace_tables(k, states):
        if k == 7:
            raise MemoryError("Unable to allocate 3.2 GiB")
        return real(k, states)

    src.trace_tables = trace_tables
    with pytest.raises(EnvironmentFailure, match=r"^out of memory .*; 5 of 10 steps are kept in .*re-run the same"):
        trace_scenario(scn, src, tmp_path / "c", steps=10, chunk_steps=5, progress=False)
    (m,) = (tmp_path / "c").glob("*/manifest.json")
    assert read_manifest(m.parent)["steps_completed"] == 5
    src.trace_tables = real
    trace_scenario(scn, src, tmp_path / "c", steps=10, chunk_steps=5, progress=False)
    assert read_manifest(m.parent)["steps_completed"] == 10

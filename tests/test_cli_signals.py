"""SIGTERM and SIGHUP end `slam run` as Ctrl-C does: every process of the run gone, no /tmp/pymp-* folder,
no temporary output, exit 143 / 129; a signal after the outputs are in place is reported, never a silent
death by signal."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.conftest import DATA, REPO

pytestmark = pytest.mark.xdist_group("pipeline")


@pytest.fixture
def tmp_path(tmp_path_factory):
    """A short temporary folder: the runs below use it as TMPDIR, where multiprocessing's forkserver puts its
    socket, and an AF_UNIX path holds at most 107 bytes (pytest's own tmp_path grows with its run counter)."""
    short = Path(tempfile.mkdtemp(prefix="sig", dir="/tmp"))
    yield short
    shutil.rmtree(short, ignore_errors=True)


def _start(args, tmp_path, code=None, tmpdir=None):
    """`python -m slam ARGS` (or `python -c CODE ARGS`) with its own TMPDIR, as if started from a shell."""
    tmp = tmpdir or tmp_path / "tmp"
    tmp.mkdir(exist_ok=True, parents=True)
    env = dict(os.environ, PYTHONPATH=str(REPO), TMPDIR=str(tmp))
    cmd = [sys.executable, "-m", "slam", *args] if code is None else [sys.executable, "-c", code, *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            preexec_fn=lambda: [signal.signal(s, signal.SIG_DFL) for s in (signal.SIGINT, signal.SIGHUP)])


def _family(pid: int) -> list[psutil.Process]:
    """The process and every descendant (stage workers, multiprocessing's forkserver and resource tracker)."""
    p = psutil.Process(pid)
    return [p, *p.children(recursive=True)]


def _running(p: psutil.Process) -> bool:
    """Still running: neither gone nor a zombie (a zombie has exited; only its parent has not reaped it)."""
    try:
        return p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


@pytest.mark.parametrize("sig,code,name", [(signal.SIGTERM, 143, "SIGTERM"), (signal.SIGHUP, 129, "SIGHUP")])
def test_termination_signal_cleans_up_like_ctrl_c(tmp_path, sig, code, name):
    """SIGTERM/SIGHUP to a real `slam run` 3 s in: exit 128 + signal with one 'error: terminated (NAME)' line,
    within 2 s no process of the run is alive, its TMPDIR holds no pymp-* folder, and neither the output
    nor a hidden temporary exists."""
    out = tmp_path / "run"
    proc = _start(["run", str(DATA / "intel.clf.bz2"), "--out", str(out), "--quiet"], tmp_path)
    try:
        first = proc.stdout.readline()
        assert first.startswith("log: "), first + proc.stderr.read()
        time.sleep(3.0)
        family = _family(proc.pid)
        assert len(family) >= 3  # the run, its forkserver and stage processes, the resource tracker
        proc.send_signal(sig)
        t0 = time.monotonic()
        _, stderr = proc.communicate(timeout=30)
        psutil.wait_procs(family, timeout=max(0.0, 2.0 - (time.monotonic() - t0)))
        alive = [p for p in family if _running(p)]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, stderr
    assert stderr.strip().splitlines()[-1] == f"error: terminated ({name})"
    assert alive == [], [p.pid for p in alive]
    assert list((tmp_path / "tmp").iterdir()) == []
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


_PATCHED_RUN = """
import os, signal, sys
import slam.pipeline.outputs as outputs
from slam.cli import main
real = outputs.write_outputs
def write_then_interrupt(*a, **k):
    folder = real(*a, **k)
    os.kill(os.getpid(), signal.SIG{sig})  # the outputs are in place: the signal lands after the final move
    return folder
outputs.write_outputs = write_then_interrupt
sys.argv = ["slam", *sys.argv[1:]]
main()
"""


@pytest.mark.parametrize("sig", ["INT", "TERM"])
def test_a_signal_after_the_final_move_is_reported(tmp_path, sig):
    """A signal that lands once the outputs are in place: the run says so on its last stderr line and exits
    128 + signal (never a silent death by signal, -2 / -15); the complete output folder stays."""
    log = DATA / "intel.clf.bz2"
    out = tmp_path / "run"
    proc = _start(["run", str(log), "--out", str(out), "--quiet", "--map", "none", "--max-scans", "30"], tmp_path,
                  code=_PATCHED_RUN.format(sig=sig))
    stdout, stderr = proc.communicate(timeout=120)
    want = 130 if sig == "INT" else 143
    assert proc.returncode == want, stderr
    assert stderr.strip().splitlines()[-1].startswith("error: ")
    assert (out / "summary.json").exists() and (out / "trajectory.tum").exists()
    assert list((tmp_path / "tmp").iterdir()) == []


def test_a_signal_during_interpreter_shutdown_does_not_kill_a_finished_command(tmp_path):
    """A SIGINT that arrives after the command has returned, while the interpreter shuts down (here: from an
    atexit hook, which runs then), cannot turn the finished command into a death by signal: exit 0."""
    code = ("import atexit, os, signal, sys, time\n"
            "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(0.2)))\n"
            "from slam.cli import main\nsys.argv = ['slam', *sys.argv[1:]]\nmain()\n")
    proc = _start(["info", str(DATA / "mit-csail.clf.bz2")], tmp_path, code=code)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, (proc.returncode, stderr)
    assert "scans: 1988" in stdout and "Traceback" not in stderr


def test_a_temporary_folder_too_long_for_the_stage_sockets_is_one_line_naming_it(tmp_path):
    """TMPDIR with a path too long for the forkserver's AF_UNIX socket: exit 2, one `error:` line that names the
    folder and what to do, no traceback, no output folder."""
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    out = tmp_path / "run"
    proc = _start(["run", str(DATA / "intel.clf.bz2"), "--out", str(out), "--quiet", "--max-scans", "20"], tmp_path,
                  tmpdir=deep)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(deep) in lines[0] and "TMPDIR" in lines[0], stderr
    assert not out.exists()


def test_a_ctrl_c_that_c_code_swallowed_stops_the_run_at_the_next_frame():
    """A SIGINT whose KeyboardInterrupt is raised inside a callback from C (libc's qsort here; numba's LLVM
    object cache in the wild) is printed as "Exception ignored" and lost; the handler also recorded it, so
    the frame loop raises it again at its next frame instead of running to the end of the log."""
    import ctypes
    import ctypes.util

    from core.frame import Frame
    from slam.cli import signals
    from slam.pipeline.config import SlamConfig
    from slam.pipeline.front_process import run_front_end

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    compare = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
    interrupted = []

    def cmp(a, b):  # type: ignore[no-untyped-def]
        if not interrupted:
            interrupted.append(True)
            os.kill(os.getpid(), signal.SIGINT)  # the handler raises here, inside the C callback
        return a[0] - b[0]

    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = 3.0 + np.sin(3 * angles)
    pts = np.c_[ranges * np.cos(angles), ranges * np.sin(angles)]
    seen: list[int] = []

    def frames():  # type: ignore[no-untyped-def]
        for k in range(30):
            if k == 3:
                values = (ctypes.c_int * 5)(5, 1, 4, 2, 3)
                # The KeyboardInterrupt raised in the comparison is printed and dropped; qsort returns here.
                libc.qsort(values, 5, ctypes.sizeof(ctypes.c_int), compare(cmp))
            yield Frame(float(k), pts, k, angles, ranges)

    cfg = SlamConfig.model_validate({"stage_processes": False})
    # As from a terminal (a test worker may run with SIGINT ignored, which terminations() leaves alone).
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with signals.terminations() as received:
            with pytest.raises(KeyboardInterrupt):
                run_front_end(frames(), cfg, lambda *item: None, lambda n, frame: seen.append(n))
    finally:
        signal.signal(signal.SIGINT, before)
    assert interrupted and received == [signal.SIGINT]
    assert seen == [1, 2, 3]  # frames 0, 1, 2 ran; frame 3's check raised the swallowed Ctrl-C

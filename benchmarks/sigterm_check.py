"""SIGTERM to a running `slam run` (issue 27's acceptance): does everything of the run end? Prints ONE JSON object.

Starts ``slam run data/intel.clf.bz2 --quiet`` as a shell would (its own TMPDIR, so multiprocessing's
``pymp-*`` folder is seen), records the run's processes (the CLI, its stage workers, multiprocessing's
forkserver and resource tracker) after ``--after`` seconds, sends SIGTERM (or ``--signal``), and measures
how long until the CLI exits and until none of those processes is running (a zombie counts as ended), what
is left in its TMPDIR (``pymp-*``) and beside the output (``.run.*.part``), the exit status and the last
stderr line. Acceptance: every process gone within 2 s, no ``pymp-*``, no ``.part``, exit 143.

Usage: ``.venv/bin/python benchmarks/sigterm_check.py [--after 8] [--repeats 3] [--signal TERM]``
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]


def _running(p: psutil.Process) -> bool:
    try:
        return p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def one(after: float, sig: signal.Signals, log: Path) -> dict:
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        tmp = work / "tmp"
        tmp.mkdir()
        out = work / "run"
        env = dict(os.environ, PYTHONPATH=str(REPO), TMPDIR=str(tmp))
        proc = subprocess.Popen([sys.executable, "-m", "slam", "run", str(log), "--out", str(out), "--quiet"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=work)
        try:
            time.sleep(after)
            root = psutil.Process(proc.pid)
            family = [root, *root.children(recursive=True)]
            pymp_before = sorted(p.name for p in tmp.iterdir())
            t0 = time.monotonic()
            proc.send_signal(sig)
            _, stderr = proc.communicate(timeout=60)
            t_exit = time.monotonic() - t0
            while any(_running(p) for p in family) and time.monotonic() - t0 < 10:
                time.sleep(0.02)
            t_all = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        return {
            "processes": len(family), "names": sorted({p.name() for p in family if _running(p)} or {"-"}),
            "exit_status": proc.returncode, "last_stderr_line": (stderr.strip().splitlines() or [""])[-1],
            "cli_exit_s": round(t_exit, 3), "all_ended_s": round(t_all, 3),
            "still_running": [p.pid for p in family if _running(p)],
            "pymp_during_run": pymp_before, "tmpdir_left": sorted(p.name for p in tmp.iterdir()),
            "output_exists": out.exists(), "hidden_left": sorted(p.name for p in work.iterdir() if p.name.startswith(".")),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--after", type=float, default=8.0, help="seconds into the run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--signal", default="TERM", choices=["TERM", "HUP", "INT"])
    ap.add_argument("--log", type=Path, default=REPO / "data" / "intel.clf.bz2")
    a = ap.parse_args()
    sig = getattr(signal, f"SIG{a.signal}")
    runs = [one(a.after, sig, a.log) for _ in range(a.repeats)]
    ok = [r["all_ended_s"] <= 2.0 and not r["still_running"] and not r["tmpdir_left"] and not r["hidden_left"]
          and not r["output_exists"] and r["exit_status"] == 128 + sig for r in runs]
    print(json.dumps({"signal": f"SIG{a.signal}", "after_s": a.after, "runs": runs,
                      "summary": {"passed": sum(ok), "of": len(runs),
                                  "max_all_ended_s": max(r["all_ended_s"] for r in runs)}}, indent=1))


if __name__ == "__main__":
    main()

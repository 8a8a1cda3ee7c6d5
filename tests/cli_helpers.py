"""Running the ``slam`` command line in the test process."""

from __future__ import annotations

import pytest

from slam.cli import main


def slam(args, capsys) -> tuple[int, str, str]:
    """``slam ARGS`` in this process: (exit status, stdout, stderr)."""
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return ei.value.code or 0, cap.out, cap.err


def one_error_line(code: int, err: str, *names: object) -> str:
    """Assert exit status 2 and exactly one ``error:`` line on stderr naming every one of *names*; return it."""
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    for n in names:
        assert str(n) in lines[0], lines[0]
    return lines[0]


def corridor_log(path, n_scans: int, seed: int):  # type: ignore[no-untyped-def]
    """A simulated corridor tour (SICK LMS laser, wheel odometry, ground truth) written as the MCAP *path*,
    with its ground-truth map beside it; returns the SimulatedLog."""
    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from slam.logs.simulated import write_simulated_log

    sim = simulate(load_world("corridor"), n_scans=n_scans, spec=LASER_PRESETS["sick_lms"], seed=seed)
    write_simulated_log(sim, path)
    return sim

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

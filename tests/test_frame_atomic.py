"""Frame invariants and atomic output: no half-written file survives an error."""

from __future__ import annotations

import numpy as np
import pytest

from core.atomic import atomic_directory, atomic_open, atomic_path
from core.errors import GeometryError
from core.frame import Frame


def test_frame_beams_and_free_endpoints():
    """No-return beams end at max range; returned beams end at their hit."""
    ang = np.linspace(-np.pi / 2, np.pi / 2, 5)
    rng_ = np.array([1.0, np.inf, 2.0, 3.0, np.inf])
    hits = np.c_[rng_ * np.cos(ang), rng_ * np.sin(ang)][np.isfinite(rng_)]
    f = Frame(stamp=1.0, points=hits, angles=ang, ranges=rng_, max_range=10.0)
    assert f.dim == 2 and f.num_beams == 5
    np.testing.assert_array_equal(f.no_return, ~np.isfinite(rng_))
    ends = f.free_endpoints()
    np.testing.assert_allclose(np.hypot(*ends.T), [1.0, 10.0, 2.0, 3.0, 10.0])
    assert f.points_3d().shape == (3, 3)


def test_frame_rejects_bad_shapes():
    with pytest.raises(GeometryError):
        Frame(stamp=0.0, points=np.zeros((4, 5)))
    with pytest.raises(GeometryError):
        Frame(stamp=0.0, points=np.zeros((0, 2)), angles=np.zeros(3), ranges=np.zeros(4))


def test_atomic_open_leaves_nothing_on_error(tmp_path):
    """An exception inside the block leaves neither the target nor a temporary file."""
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_open(target) as fh:
            fh.write("partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_open(target) as fh:
        fh.write("done")
    assert target.read_text() == "done"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_path_keeps_old_file_on_error(tmp_path):
    """A failed rewrite keeps the previous complete file."""
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")
    with pytest.raises(ValueError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new-but-broken")
            raise ValueError
    assert target.read_bytes() == b"old"


def test_atomic_directory(tmp_path):
    """Files appear in the output folder only after the block succeeded."""
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        with atomic_directory(out) as d:
            (d / "x.txt").write_text("1")
            raise KeyboardInterrupt
    assert not out.exists() or not any(out.iterdir())
    with atomic_directory(out) as d:
        (d / "x.txt").write_text("1")
        (d / "sub").mkdir()
        (d / "sub" / "y.txt").write_text("2")
    assert (out / "x.txt").read_text() == "1" and (out / "sub" / "y.txt").read_text() == "2"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_atomic_output_has_umask_permissions(tmp_path):
    """Atomic files get the permissions of an ordinary open() (0666 & ~umask), not mkstemp's 0600."""
    import os

    mask = os.umask(0o022)
    try:
        with atomic_open(tmp_path / "f.txt") as fh:
            fh.write("x")
    finally:
        os.umask(mask)
    assert (tmp_path / "f.txt").stat().st_mode & 0o777 == 0o644


@pytest.fixture
def default_sigint():
    """Python's own SIGINT handler (KeyboardInterrupt) for the test, whatever the test runner set."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_while_moving_in_is_held_until_every_file_is_there(tmp_path, monkeypatch, default_sigint):
    """A real SIGINT arriving while a run's folder replaces a previous run's: the KeyboardInterrupt comes
    only after the new folder is in place (all new files, none old), and no temporary folder is left."""
    import os
    import signal

    import core.atomic as atomic

    out = tmp_path / "run"
    with atomic_directory(out) as d:
        for name in ("a.txt", "b.txt", "c.txt"):
            (d / name).write_text("old")
    real_replace = atomic._replace_folder
    calls = []

    def replace_and_interrupt(new, target):  # the user presses Ctrl-C as the folder is moved
        os.kill(os.getpid(), signal.SIGINT)
        calls.append(target)
        return real_replace(new, target)

    monkeypatch.setattr(atomic, "_replace_folder", replace_and_interrupt)
    with pytest.raises(KeyboardInterrupt):
        with atomic_directory(out) as d:
            for name in ("a.txt", "b.txt", "c.txt"):
                (d / name).write_text("new")
    assert calls == [out]
    assert [(out / n).read_text() for n in ("a.txt", "b.txt", "c.txt")] == ["new"] * 3
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is restored


def test_new_folder_appears_in_one_step(tmp_path, monkeypatch):
    """A folder that did not exist is the temporary folder renamed (no file-by-file move)."""
    import os

    import core.atomic as atomic

    moved = []
    monkeypatch.setattr(atomic.os, "replace", lambda s, d: moved.append(d) or os.rename(s, d))
    with atomic_directory(tmp_path / "new") as d:
        (d / "x.txt").write_text("1")
    assert moved == [] and (tmp_path / "new" / "x.txt").read_text() == "1"
    assert [p.name for p in tmp_path.iterdir()] == ["new"]

"""Help texts: every option's help is shown whole (rich markup must not eat '[s]'), every command says what it
does in a sentence, and the progress bar ends on the counts the summary reports."""

from __future__ import annotations

import json

import pytest
import typer

from slam.cli import app
from tests.cli_helpers import corridor_log, slam


def _commands():
    """(command path, click command) of every subcommand."""
    root = typer.main.get_command(app)
    out = []
    for name, cmd in root.commands.items():
        subs = getattr(cmd, "commands", None)
        if subs:
            out += [((name, sub), c) for sub, c in subs.items()]
        else:
            out.append(((name,), cmd))
    return out


COMMANDS = _commands()


def _flat(text: str) -> str:
    return " ".join(text.replace("│", " ").split())


@pytest.mark.parametrize("path,cmd", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_every_option_help_is_shown_whole(path, cmd, capsys, monkeypatch):
    """`slam … --help` (wide terminal) shows each option's help text word for word: '[s]' and '[m]' were read as
    rich markup and vanished ('association .')."""
    monkeypatch.setenv("COLUMNS", "400")
    code, out, _ = slam([*path, "--help"], capsys)
    assert code == 0
    shown = _flat(out)
    for p in cmd.params:
        if getattr(p, "help", None):
            assert _flat(p.help) in shown, (p.name, p.help)


@pytest.mark.parametrize("path,cmd", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_every_command_says_what_it_does(path, cmd):
    """The first paragraph of each command's help says in words what it does: at least six words outside code
    spans (`slam solve --help` was only a list of JSON keys: 'Print ``{"sesync_objective", ...}`` on one line.')."""
    import re

    first = " ".join((cmd.help or "").strip().split("\n\n")[0].split())
    words = re.sub(r"``.*?``", " ", first).split()
    assert len(words) >= 6, first


def test_progress_bar_ends_on_the_summary_counts(tmp_path, capsys, monkeypatch):
    """The bar's last update carries the run's final scan and keyframe counts (it stopped at the last
    multiple of 25 scans, before the final keyframes: 73 against the summary's 84 in the issue)."""
    import rich.progress

    updates: list[dict] = []

    class Recording(rich.progress.Progress):
        def update(self, task_id, **kw):  # type: ignore[no-untyped-def]
            updates.append(kw)
            super().update(task_id, **kw)

    monkeypatch.setattr(rich.progress, "Progress", Recording)
    log = tmp_path / "c.mcap"
    corridor_log(log, 62, seed=8)
    code, _, err = slam(["run", log, "--out", tmp_path / "run", "--map", "none"], capsys)
    assert code == 0, err
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    last = updates[-1]
    assert (last["completed"], last["kf"], last["lc"]) == (s["scans"], s["keyframes"], s["loop_closures"])

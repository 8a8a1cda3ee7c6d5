"""The ``slam`` command line (typer). Each command lives in its own module of this package.

A module registers its commands with ``register(app, eval_app)``; heavy imports happen inside
the command functions so that ``slam --help`` stays fast. Any :class:`GpslamError`, and any bad command
line, is printed as one line ``error: <file>:<position>: <what>`` on stderr with exit status 2.
"""

from __future__ import annotations

import errno
import importlib
import sys
import warnings

import typer

from core.errors import GpslamError
from slam import __version__

from . import signals

# Command modules, in help order. Each defines register(app, eval_app).
COMMAND_MODULES = (
    "slam.cli.info_cmd",
    "slam.cli.demo_cmd",
    "slam.cli.eval_cmd",
    "slam.cli.simulate_cmd",
    "slam.cli.solve_cmd",
    "slam.cli.map_cmd",
    "slam.cli.run_cmd",
    "slam.cli.loops_cmd",
    "slam.cli.batch_cmd",
)

app = typer.Typer(
    name="slam",
    help="gpslam: SLAM on robot logs — registration, pose graphs, Gaussian-process occupancy maps.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)
eval_app = typer.Typer(help="Evaluate trajectories, relations, maps and runs.", no_args_is_help=True)
app.add_typer(eval_app, name="eval")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"gpslam {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """gpslam command line."""


for _name in COMMAND_MODULES:
    importlib.import_module(_name).register(app, eval_app)


def _interrupted(exc: BaseException) -> bool:
    """True when *exc* is, or was raised while handling, a KeyboardInterrupt (e.g. a C extension's
    import failing because Ctrl-C arrived during its initialisation)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:  # type: ignore[no-untyped-def]
    """``warnings.showwarning`` of the CLI: ``warning: <message>`` on one stderr line."""
    print(f"warning: {' '.join(str(message).split())}", file=sys.stderr if file is None else file)


# click's base of every command-line error (usage errors, bad option values); typer vendors click, and
# exports only BadParameter of its exceptions.
_USAGE_ERRORS = tuple(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


def _error(text: str) -> None:
    print(f"error: {' '.join(str(text).split())}", file=sys.stderr)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the typer app and exit with its status.

    Project errors and bad command lines (click's usage errors: an unknown option, a bad option value) are
    one ``error:`` line and exit 2; warnings are one ``warning:`` line each; SIGINT, SIGTERM and SIGHUP end
    the command cleanly with 128 + the signal number (:mod:`slam.cli.signals`). Run as the console script
    (*argv* None), the signals are ignored once the command is done, so the interpreter's shutdown cannot be
    killed by a late one.
    """
    with warnings.catch_warnings(), signals.terminations() as received:
        warnings.showwarning = _warning_line
        try:
            code = _run(argv, received)
        finally:
            if argv is None:
                signals.ignore_held_signals()
    sys.exit(code)


def _run(argv: list[str] | None, received: list[int]) -> int:
    """The exit status of the command (errors printed)."""
    try:
        rv = app(args=argv, prog_name="slam", standalone_mode=False)
    except _USAGE_ERRORS as exc:
        ctx = getattr(exc, "ctx", None)
        if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:  # 'slam' or 'slam eval' alone
            typer.echo(ctx.get_help())
            return 2
        hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
        _error(f"{exc.format_message()}{hint}")
        return 2
    except GpslamError as exc:
        _error(str(exc))
        return 2
    except (KeyboardInterrupt, typer.Abort):
        _error(signals.message(received))
        return signals.exit_code(received)
    except OSError as exc:  # what no reader or writer turned into a project error: still one line
        if exc.errno == errno.EPIPE:  # stdout closed early (slam ... | head): nothing to say
            return 1
        _error(f"{exc.filename}: {exc.strerror}" if exc.filename is not None else str(exc))
        return 2
    except Exception as exc:
        if not _interrupted(exc):
            raise
        _error(signals.message(received))
        return signals.exit_code(received)
    if rv == 130:  # typer turns a KeyboardInterrupt inside a command into exit 130 (no command exits 130 itself)
        _error(signals.message(received))
        return signals.exit_code(received)
    return rv if isinstance(rv, int) else 0

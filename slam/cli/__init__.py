"""The ``slam`` command line (typer). Each command lives in its own module of this package.

A module registers its commands with ``register(app, eval_app)``; heavy imports happen inside
the command functions so that ``slam --help`` stays fast. Any :class:`GpslamError` is printed
as one line ``error: <file>:<position>: <what>`` on stderr with exit status 2.
"""

from __future__ import annotations

import importlib
import sys
import warnings

import typer

from registration.errors import GpslamError
from slam import __version__

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


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the typer app, turning project errors into one line and exit 2, and
    showing warnings as one ``warning:`` line each."""
    with warnings.catch_warnings():
        warnings.showwarning = _warning_line
        _main(argv)


def _main(argv: list[str] | None) -> None:
    try:
        app(args=argv, prog_name="slam")
    except GpslamError as exc:
        msg = " ".join(str(exc).split())
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
    except SystemExit as exc:
        # typer turns a KeyboardInterrupt inside a command into a silent exit 130 (and no command
        # exits 130 on its own): say why.
        if exc.code == 130:
            print("error: interrupted", file=sys.stderr)
        raise
    except Exception as exc:
        if not _interrupted(exc):
            raise
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)

"""Turn exceptions into one-line messages and exit codes (tracebacks only with -vv)."""

from __future__ import annotations

import re
import signal
import sys
import traceback

import click

from ..errors import EXIT_DATA, EXIT_SIGINT, EXIT_USAGE, StereoError, excerpt


def _verbosity(argv: list[str], flag: str = "v") -> int:
    """How many times ``-v`` (or ``flag``) appears in ``argv``, before Click parses it."""
    long = {"v": "--verbose", "q": "--quiet"}[flag]
    level = 0
    for arg in argv:
        if arg == long:
            level += 1
        elif arg.startswith("-") and not arg.startswith("--") and set(arg[1:]) == {flag}:
            level += len(arg) - 1
    return level


def run_captured(cli: click.Group, argv: list[str] | None = None) -> int:
    """:func:`run_with_error_handling` as the console entry point runs it: SIGINT and SIGTERM
    stop the command cleanly (exit 130/143), and output third-party code writes straight to
    stderr (libpng, OpenCV, worker processes, Python warnings) is collected and reported after
    the command: one line saying how much there was, or all of it with ``-v`` (``-vv`` shows
    it as it happens)."""
    from ..process import capture_native_stderr, interrupts_raise

    argv = list(sys.argv[1:] if argv is None else argv)
    verbose, quiet = _verbosity(argv), _verbosity(argv, "q")
    noise = capture_native_stderr(enabled=verbose < 2)
    try:
        with interrupts_raise(), noise:
            code = run_with_error_handling(cli, argv)
    except KeyboardInterrupt as exc:  # arrived after the command ended, while cleaning up
        code = getattr(exc, "exit_code", EXIT_SIGINT)
    lines = noise.lines()
    if lines and verbose >= 1:
        click.echo(f"third-party output ({len(lines)} lines):", err=True)
        for line in lines:
            click.echo(f"  {line}", err=True)
    elif lines and quiet == 0:
        click.echo(f"Note: {len(lines)} line(s) of third-party output hidden (first: {lines[0].strip()[:100]!r}); "
                   "-v shows them", err=True)
    return code


def run_with_error_handling(cli: click.Group, argv: list[str] | None = None) -> int:
    """Run ``cli`` and return the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    verbose = _verbosity(argv)
    try:
        # With standalone_mode=False Click *returns* the code of ctx.exit(n) instead of raising.
        rv = cli.main(args=argv, prog_name="stereocli", standalone_mode=False)
        return rv if isinstance(rv, int) else 0
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        # Click's own messages quote an option's value whole. (Click types `message` as Final, yet its
        # exceptions are built to be shown after the fact: setting it is what show() reads.)
        exc.message = _short_values(exc.message)  # type: ignore[misc]
        exc.show()
        return exc.exit_code
    except click.exceptions.Abort as exc:
        cause = exc.__cause__ or exc.__context__
        if isinstance(cause, KeyboardInterrupt):  # Click's name for an interrupt
            return _interrupted(cause)
        click.echo("Aborted.", err=True)
        return EXIT_DATA
    except StereoError as exc:
        if verbose >= 2:
            traceback.print_exc()
        click.echo(_short_values(f"Error: {exc}"), err=True)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    except OSError as exc:  # disk full, permissions: name the file
        if verbose >= 2:
            traceback.print_exc()
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(_short_values(f"Error: {where}{exc.strerror or exc}"), err=True)
        return EXIT_DATA
    except Exception as exc:  # noqa: BLE001 - last resort: one line unless -vv
        if verbose >= 2:
            traceback.print_exc()
        click.echo(_short_values(f"Error: {type(exc).__name__}: {exc} (run with -vv for the traceback)"), err=True)
        return EXIT_DATA


#: Runs of non-blank characters longer than this are no path (PATH_MAX on Linux): a value a
#: message quotes whole, shortened to an excerpt.
_LONGEST_PATH = 4096


def _short_values(message: str) -> str:
    """``message`` with every run of non-blank characters longer than any path shortened to an
    :func:`~stereocli.errors.excerpt`: the last guard for values no error site shortened itself
    (Click quotes an option's value whole; an OS error names a file name too long to exist)."""
    def shorten(match: re.Match) -> str:
        value = match.group()
        return excerpt(value.rstrip(":")) + (":" if value.endswith(":") else "")

    return re.sub(r"\S{%d,}" % (_LONGEST_PATH + 1), shorten, message)


def _interrupted(exc: KeyboardInterrupt) -> int:
    """Report an interrupt that reached the command line; returns 130 (SIGINT) or 143 (SIGTERM)."""
    code = getattr(exc, "exit_code", EXIT_SIGINT)
    click.echo(f"Interrupted ({signal.Signals(code - 128).name}).", err=True)
    return code


def usage_error(message: str) -> click.UsageError:
    """A Click usage error (exit 2) with our message."""
    err = click.UsageError(message)
    err.exit_code = EXIT_USAGE  # type: ignore[misc]  # Click types it per class; this instance's code is ours
    return err

"""Turn exceptions into one-line messages and exit codes (tracebacks only with -vv)."""

from __future__ import annotations

import sys
import traceback

import click

from ..errors import EXIT_DATA, EXIT_USAGE, StereoError


def _verbosity(argv: list[str]) -> int:
    level = 0
    for arg in argv:
        if arg == "--verbose":
            level += 1
        elif arg.startswith("-") and not arg.startswith("--") and set(arg[1:]) == {"v"}:
            level += len(arg) - 1
    return level


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
        exc.show()
        return exc.exit_code
    except click.exceptions.Abort:
        click.echo("Aborted.", err=True)
        return EXIT_DATA
    except StereoError as exc:
        if verbose >= 2:
            traceback.print_exc()
        click.echo(f"Error: {exc}", err=True)
        return exc.exit_code
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        return 130
    except Exception as exc:  # noqa: BLE001 - last resort: one line unless -vv
        if verbose >= 2:
            traceback.print_exc()
        click.echo(f"Error: {type(exc).__name__}: {exc} (run with -vv for the traceback)", err=True)
        return EXIT_DATA


def usage_error(message: str) -> click.UsageError:
    """A Click usage error (exit 2) with our message."""
    err = click.UsageError(message)
    err.exit_code = EXIT_USAGE
    return err

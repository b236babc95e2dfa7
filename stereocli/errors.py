"""Exception types and the exit codes the command line maps them to.

The library raises these; ``stereocli.cli`` turns them into a one-line message and an exit
code (no traceback unless ``-vv``).
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_DATA = 1  # unreadable input, runtime failure
EXIT_USAGE = 2  # bad command line or configuration
EXIT_PARTIAL = 3  # a batch finished but some items failed


class StereoError(Exception):
    """Base class; ``exit_code`` tells the CLI how to exit."""

    exit_code = EXIT_DATA


class DataError(StereoError):
    """Input data is missing, unreadable, inconsistent or corrupt (exit 1)."""

    exit_code = EXIT_DATA


class ConfigError(StereoError):
    """A configuration, option or stage parameter is invalid (exit 2)."""

    exit_code = EXIT_USAGE


class OutputExistsError(StereoError):
    """An output exists and neither ``--overwrite`` nor ``--skip-existing`` was given (exit 1)."""

    exit_code = EXIT_DATA


class MemoryBudgetError(ConfigError):
    """The requested setting cannot fit in the memory budget (exit 2)."""

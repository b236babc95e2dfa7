"""Exception types and the exit codes the command line maps them to.

The library raises these; ``stereocli.cli`` turns them into a one-line message and an exit
code (no traceback unless ``-vv``).
"""

from __future__ import annotations

import difflib
import os
from typing import Iterable

EXIT_OK = 0
EXIT_DATA = 1  # unreadable input, runtime failure
EXIT_USAGE = 2  # bad command line or configuration
EXIT_PARTIAL = 3  # a batch finished but some items failed
EXIT_SIGINT = 130  # interrupted (Ctrl-C): 128 + SIGINT
EXIT_SIGTERM = 143  # terminated: 128 + SIGTERM


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


class OutputLockedError(StereoError):
    """Another live run holds the output folder's lock file (exit 1)."""

    exit_code = EXIT_DATA


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; ``exit_code`` is 128 + the signal number (130, 143).

    A :class:`KeyboardInterrupt`, so code that already stops cleanly on Ctrl-C stops on it too.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


#: The most characters of a user's value an error message quotes: a hostile value (a 100 KB
#: ``--set``, a garbled calib.txt line) is named by its start and its length, never echoed whole.
EXCERPT_CHARS = 60


def named(name: str, message: str) -> str:
    """``message`` after ``name: `` (the pair or scene it is about), or alone without a name."""
    return f"{name}: {message}" if name else message


def excerpt(value: object, *, quote: bool = False, limit: int = EXCERPT_CHARS) -> str:
    """How an error message quotes a user's ``value``: a string as it is (``repr`` with ``quote``,
    and any other value always), cut after ``limit`` characters with the length of the whole.

    >>> excerpt("[" * 1000)
    '[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[… (1000 characters)'
    """
    text = repr(value) if quote or not isinstance(value, str) else value
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text)} characters)"


def close_matches(word: str, options: Iterable[str]) -> list[str]:
    """Up to three of ``options`` that look like ``word`` (for "did you mean" hints)."""
    return difflib.get_close_matches(str(word), [str(o) for o in options], n=3, cutoff=0.5)


def did_you_mean(word: str, options: Iterable[str]) -> str:
    """`` (did you mean 'a' or 'b'?)`` for the close matches of ``word``, or ``""``."""
    close = close_matches(word, options)
    return f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""


def check_outputs_free(paths: Iterable[str | os.PathLike], *, overwrite: bool,
                       hint: str = "use --overwrite to replace") -> None:
    """The one overwrite policy: raise :class:`OutputExistsError` naming the first existing path
    (and how many more) unless ``overwrite``."""
    if overwrite:
        return
    clashes = [str(p) for p in paths if os.path.lexists(p)]
    if clashes:
        more = f" and {len(clashes) - 1} more" if len(clashes) > 1 else ""
        verb = "already exist" if clashes[1:] else "already exists"
        raise OutputExistsError(f"{clashes[0]}{more} {verb}; {hint}")

"""One run at a time per output folder: a lock file holding the owner's pid and host.

``OUTDIR/.stereocli.lock`` is created exclusively when a batch starts and removed when it ends.
A second run into the same folder stops at once with :class:`~stereocli.errors.OutputLockedError`
(exit 1) naming the owner. A lock left by a run that died (its pid is gone on this host, or now
belongs to a process started later) is stale and taken over, and so is a dangling symbolic link
in its place; a lock from another host is never second-guessed (delete it by hand if that run
is gone). A lock that cannot be written whole (a full disk) is removed again, with an error.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Iterator

from ..errors import DataError, OutputLockedError

LOCK_NAME = ".stereocli.lock"
#: A lock file still empty after this long was left by a run killed while creating it.
EMPTY_STALE_SECONDS = 10.0


def _start_ticks(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux), to tell a reused pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner_info() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "start_ticks": _start_ticks(os.getpid()), "argv": ["stereocli", *sys.argv[1:]]}


def _read(path: Path) -> dict | None:
    """The lock's owner, ``{}`` when the file is empty or unreadable, None when it is gone
    (a dangling symbolic link is ``{"dangling": True}``)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {"dangling": True} if path.is_symlink() else None
    except OSError:
        return {}
    try:
        data = json.loads(text)
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def _is_stale(path: Path, owner: dict) -> bool:
    if owner.get("dangling"):  # a link to nothing: no run holds it
        return True
    if not owner:  # empty: being written right now, or its writer was killed
        try:
            return time.time() - path.stat().st_mtime > EMPTY_STALE_SECONDS
        except OSError:
            return False
    if owner.get("host") != socket.gethostname() or not isinstance(owner.get("pid"), int):
        return False
    pid = owner["pid"]
    if not _alive(pid):
        return True
    ticks = owner.get("start_ticks")
    return ticks is not None and _start_ticks(pid) not in (None, ticks)


def _describe(folder: Path, owner: dict) -> str:
    if not owner:
        return f"{folder}: another stereocli run is starting in this output folder ({folder / LOCK_NAME})"
    command = " ".join(owner.get("argv", [])[:3])
    return (f"{folder}: in use by another run (pid {owner.get('pid')} on {owner.get('host')}, since "
            f"{owner.get('started')}{', ' + command if command else ''}); wait for it to finish, or delete "
            f"{folder / LOCK_NAME} if that run is gone")


@contextlib.contextmanager
def output_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold ``folder``'s lock for the block (creating the folder; removing it again on exit if
    this run created it and left it empty). Raises :class:`OutputLockedError` when a live run
    holds it."""
    folder = Path(folder)
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    mine = _owner_info()
    try:
        _acquire(folder, path, mine)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    try:
        yield path
    finally:
        owner = _read(path)
        if owner and owner.get("pid") == mine["pid"] and owner.get("host") == mine["host"]:
            path.unlink(missing_ok=True)
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()


def _acquire(folder: Path, path: Path, mine: dict) -> None:
    data = (json.dumps(mine) + "\n").encode()
    for _ in range(5):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _read(path)
            if owner is None:
                continue  # released meanwhile: try again
            if not _is_stale(path, owner):
                raise OutputLockedError(_describe(folder, owner)) from None
            # Stale: move it aside (one taker wins the rename), then create ours.
            aside = path.with_name(f"{LOCK_NAME}.stale-{os.getpid()}")
            try:
                os.rename(path, aside)
            except FileNotFoundError:
                continue
            aside.unlink(missing_ok=True)
            continue
        try:
            _write_all(fd, data)
            os.fsync(fd)
        except BaseException as exc:
            os.close(fd)
            path.unlink(missing_ok=True)  # an empty or torn lock would hold off every run
            if isinstance(exc, OSError):
                raise DataError(f"{path}: cannot write the lock file ({exc.strerror or exc})") from None
            raise
        os.close(fd)
        return
    raise OutputLockedError(_describe(folder, _read(path) or {}))


def _write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` (a write may take only part of it, e.g. at a file-size limit)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]

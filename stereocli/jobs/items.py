"""Work items and their outcomes, the per-item runner, and the output policy of a batch.

Item functions take one :class:`WorkItem`, write its outputs atomically
(:mod:`stereocli.io.atomic`) and return a JSON-able dict of details for the run record. They
must be importable top-level functions: process pools and Dask pickle them by name.
"""

from __future__ import annotations

import glob
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..errors import EXIT_OK, EXIT_PARTIAL, StereoError, check_outputs_free

RESUME_HINT = "use --overwrite to replace or --skip-existing to resume"


@dataclass
class WorkItem:
    """One unit of work: a name, input paths, output paths and per-item options."""

    name: str
    inputs: dict[str, str]
    outputs: dict[str, str]
    options: dict[str, Any] = field(default_factory=dict)

    def existing_outputs(self) -> list[str]:
        return [p for p in self.outputs.values() if Path(p).exists()]

    def as_dict(self) -> dict[str, Any]:
        """``name``, ``inputs``, ``outputs``, ``options`` (the ``--dry-run`` plan of one item)."""
        return asdict(self)


@dataclass
class ItemResult:
    """Outcome of one item: ``status`` is ``ok``, ``skipped`` or ``failed`` (with ``message``)."""

    name: str
    status: str
    seconds: float = 0.0
    message: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    attempts: int = 0

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def failure(cls, item: WorkItem, message: str) -> "ItemResult":
        """A failed outcome for ``item`` that never produced a result (dead worker, lost task)."""
        return cls(item.name, "failed", message=message, inputs=item.inputs, outputs=item.outputs)


@dataclass
class BatchResult:
    """Per-item outcomes in input order."""

    results: list[ItemResult]

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def exit_code(self) -> int:
        return EXIT_PARTIAL if self.failed else EXIT_OK


def check_outputs(items: list[WorkItem], *, overwrite: bool, skip_existing: bool) -> None:
    """Refuse (before any work starts) when outputs exist and neither policy was chosen."""
    if skip_existing:
        return
    check_outputs_free([p for item in items for p in item.outputs.values()], overwrite=overwrite,
                       hint=RESUME_HINT)


def is_done(item: WorkItem) -> bool:
    """True when every output of ``item`` exists (``--skip-existing`` skips it)."""
    return bool(item.outputs) and len(item.existing_outputs()) == len(item.outputs)


def run_one(item_fn: Callable[[WorkItem], dict], item: WorkItem, verbose_errors: bool) -> ItemResult:
    """Run ``item_fn(item)``; any exception becomes a failed outcome with a one-line message
    (plus the traceback with ``verbose_errors``). Seconds are wall-clock."""
    t0 = time.perf_counter()
    try:
        remove_temporaries(item)  # left by an attempt whose process died (killed worker, earlier run)
        details = item_fn(item) or {}
        status, message = "ok", ""
    except StereoError as exc:
        details, status, message = {}, "failed", str(exc)
    except MemoryError:
        details, status, message = {}, "failed", "out of memory"
    except Exception as exc:  # noqa: BLE001 - one item's bug must not kill the batch
        details, status = {}, "failed"
        message = f"{type(exc).__name__}: {exc}"
        if verbose_errors:
            message += "\n" + traceback.format_exc()
    return ItemResult(item.name, status, round(time.perf_counter() - t0, 4), message, details,
                      item.inputs, item.outputs, 1)


def remove_temporaries(item: WorkItem) -> None:
    """Delete temporary files a dead attempt may have left beside ``item``'s outputs.

    Matches only the names :func:`stereocli.io.atomic.atomic_path` gives the temporaries of
    these outputs (``.<stem>.<8 random chars>.tmp<suffix>``, from :func:`tempfile.mkstemp`), never
    files under final names nor temporaries of other outputs in the same folder.
    """
    for out in item.outputs.values():
        path = Path(out)
        if path.parent.is_dir():
            for tmp in path.parent.glob(f".{glob.escape(path.stem)}.{'?' * 8}.tmp{glob.escape(path.suffix)}"):
                tmp.unlink(missing_ok=True)


def prepare_worker() -> None:
    """Process-wide settings every worker process gets before running items: freed large
    buffers stay in the process between items (:mod:`stereocli.process`)."""
    from ..process import keep_freed_memory

    keep_freed_memory()

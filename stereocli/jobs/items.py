"""Work items and their outcomes, the per-item runner, and the output policy of a batch.

Item functions take one :class:`WorkItem`, write its outputs (:mod:`stereocli.io.atomic`) and
return a JSON-able dict of details for the run record. They must be importable top-level
functions: process pools and Dask pickle them by name.

An item's outputs are committed together (:func:`run_one`): the item function writes them into
a fresh hidden staging folder ``.stereocli-tmp/<name>.<random>.<run>.stage`` beside the item's
folder, and only when it succeeds are they moved into place, with a completion marker
``.stereocli-<command>.done`` listing them. A folder that holds nothing but this command's
outputs is replaced whole by one rename, so a reader (or a kill) sees the old set, no folder, or
the new set; a folder shared with other files (e.g. ``match`` writing beside ``rectify``'s
images) gets its files replaced one by one, marker removed first and written last.
The marker also records what made the item (:func:`marker_matches`): the stereocli ``version``,
a digest of the settings that change its outputs (``config``, from :attr:`WorkItem.config_digest`)
and the size and modification time of each input (``inputs``). ``--skip-existing`` counts an
item done only when its marker and every output exist and the marker matches; it redoes the
others (:func:`stale_reason` says why).
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import shutil
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from .. import __version__
from ..errors import EXIT_DATA, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, ConfigError, StereoError, check_outputs_free
from ..io.atomic import plain_mode, write_text

RESUME_HINT = "use --overwrite to replace or --skip-existing to resume"
#: Hidden folder (beside the items' folders) holding outputs being written.
STAGING = ".stereocli-tmp"


@dataclass
class WorkItem:
    """One unit of work: a name, input paths, output paths and per-item options.

    ``folder`` is the item's own output folder (its outputs are committed together and marked
    complete with ``.stereocli-<command>.done``, which records ``run_id``); ``error`` is set when
    planning the item failed: it fails with that message and exit code ``error_code``, without
    running. ``config_digest`` (:func:`settings_digest`) covers the settings that change the
    item's outputs; its marker records it.
    """

    name: str
    inputs: dict[str, str]
    outputs: dict[str, str]
    options: dict[str, Any] = field(default_factory=dict)
    folder: str = ""
    command: str = ""
    error: str = ""
    error_code: int = EXIT_DATA
    run_id: str = ""
    config_digest: str = ""

    def existing_outputs(self) -> list[str]:
        return [p for p in self.outputs.values() if Path(p).exists()]

    def as_dict(self) -> dict[str, Any]:
        """``name``, ``inputs``, ``outputs``, ``options`` (the ``--dry-run`` plan of one item)."""
        out = {"name": self.name, "inputs": self.inputs, "outputs": self.outputs, "options": self.options}
        if self.error:
            out["error"] = self.error
        return out

    def absolute(self) -> WorkItem:
        """The same item with absolute input and output paths (workers may run elsewhere)."""
        return replace(self, inputs={k: os.path.abspath(v) for k, v in self.inputs.items()},
                       outputs={k: os.path.abspath(v) for k, v in self.outputs.items()},
                       folder=os.path.abspath(self.folder) if self.folder else "")

    @property
    def marker(self) -> Path | None:
        """The completion marker of an item with a folder."""
        return Path(self.folder) / f".stereocli-{self.command or 'batch'}.done" if self.folder else None


@dataclass
class ItemResult:
    """Outcome of one item: ``status`` is ``ok``, ``skipped`` or ``failed`` (with ``message`` and
    the ``exit_code`` its error maps to: 1 data/runtime, 2 usage/configuration)."""

    name: str
    status: str
    seconds: float = 0.0
    message: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    attempts: int = 0
    exit_code: int = EXIT_OK

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def failure(cls, item: WorkItem, message: str, exit_code: int = EXIT_DATA) -> ItemResult:
        """A failed outcome for ``item`` that never produced a result (dead worker, lost task)."""
        return cls(item.name, "failed", message=label_message(item.name, message), inputs=item.inputs,
                   outputs=item.outputs, exit_code=exit_code)


@dataclass
class BatchResult:
    """Per-item outcomes in input order. When the batch was interrupted (``interrupted`` is the
    signal number), ``results`` holds only the items that finished, of ``total``."""

    results: list[ItemResult]
    interrupted: int | None = None
    total: int | None = None

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def exit_code(self) -> int:
        """128 + signal when interrupted; 0 all ok; 3 some failed; when nothing succeeded, 2 if
        every failure was a usage/configuration error, else 1."""
        if self.interrupted:
            return 128 + self.interrupted
        return batch_exit_code(self.results)


def batch_exit_code(results: list[ItemResult]) -> int:
    """The exit code of a finished batch of ``results`` (see :attr:`BatchResult.exit_code`)."""
    failed = [r for r in results if r.status == "failed"]
    if not failed:
        return EXIT_OK
    if any(r.status in ("ok", "skipped") for r in results):
        return EXIT_PARTIAL
    return EXIT_USAGE if all(r.exit_code == EXIT_USAGE for r in failed) else EXIT_DATA


def check_outputs(items: list[WorkItem], *, overwrite: bool, skip_existing: bool) -> None:
    """Refuse (before any work starts) when outputs exist and neither policy was chosen."""
    if skip_existing:
        return
    check_outputs_free([p for item in items for p in item.outputs.values()], overwrite=overwrite,
                       hint=RESUME_HINT)


def is_done(item: WorkItem) -> bool:
    """True when every output of ``item`` exists, and for an item with a folder its completion
    marker too, recording what this run would make the item from (:func:`marker_matches`):
    ``--skip-existing`` skips it."""
    if not item.outputs or len(item.existing_outputs()) != len(item.outputs):
        return False
    return item.marker is None or marker_matches(item)[0]


def settings_digest(settings: dict[str, Any]) -> str:
    """A short digest (16 hex digits) of ``settings``, the JSON-able settings that change an
    item's outputs (never jobs, threads or progress): :attr:`WorkItem.config_digest`."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def input_stamps(inputs: dict[str, str]) -> dict[str, list[int] | None]:
    """``{key: [size in bytes, modification time in ns]}`` of each input path (None when it
    cannot be read): what a completion marker records of the inputs."""
    stamps: dict[str, list[int] | None] = {}
    for key, path in inputs.items():
        try:
            st = os.stat(path)
        except OSError:
            stamps[key] = None
            continue
        stamps[key] = [st.st_size, st.st_mtime_ns]
    return stamps


def marker_matches(item: WorkItem) -> tuple[bool, str]:
    """Whether ``item``'s completion marker records what this process would make the item
    from: this stereocli version, ``item.config_digest`` and inputs of the same size and
    modification time. Returns ``(True, "")``, or ``(False, reason)`` with a short phrase.
    An item without a folder keeps no marker: ``(True, "")``."""
    marker = item.marker
    if marker is None:
        return True, ""
    try:
        data = json.loads(marker.read_text())
    except FileNotFoundError:
        return False, "no completion marker"
    except (OSError, ValueError):
        return False, f"unreadable completion marker {marker.name}"
    if not isinstance(data, dict) or not all(k in data for k in ("version", "config", "inputs")):
        return False, "its marker records no settings or inputs (an older stereocli made it)"
    if data["version"] != __version__:
        return False, f"made by stereocli {data['version']} (this is {__version__})"
    if data["config"] != item.config_digest:
        return False, "made with other settings (config or options)"
    recorded = data["inputs"] if isinstance(data["inputs"], dict) else {}
    for key, stamp in input_stamps(item.inputs).items():
        if key not in recorded:
            return False, f"made without the {key} input {item.inputs[key]}"
        if recorded[key] != stamp:
            return False, f"the {key} input {item.inputs[key]} changed since (size or modification time)"
    extra = sorted(set(recorded) - set(item.inputs))
    if extra:
        return False, f"made with a {extra[0]} input too"
    return True, ""


def stale_reason(item: WorkItem) -> str:
    """Why ``--skip-existing`` redoes ``item`` although an earlier run left outputs of it
    (the marker does not match, or some outputs are missing); ``""`` when it skips the item,
    when nothing of it exists yet, and for items whose planning failed."""
    if item.error or not item.outputs:
        return ""
    existing = item.existing_outputs()
    marked = item.marker is not None and os.path.lexists(item.marker)
    if not existing and not marked:
        return ""
    if len(existing) != len(item.outputs):
        missing = next(p for p in item.outputs.values() if p not in existing)
        return f"{Path(missing).name} is missing"
    return marker_matches(item)[1]


def check_output_paths(items: list[WorkItem], outdir: str | os.PathLike | None = None) -> None:
    """Refuse a plan that writes where it must not, before any work: an output that is (once
    resolved) an input of any item, and with ``outdir`` an output outside it once resolved
    (a symbolic link), or in the place of the batch's own files (run record, lock, staging
    folder, markers). Raises :class:`~stereocli.errors.ConfigError` naming the item and path."""
    from ..io.pairs import RESERVED_NAMES
    from .lock import LOCK_NAME

    inputs = {os.path.realpath(path): path for item in items for path in item.inputs.values()}
    root = os.path.realpath(outdir) if outdir is not None else None
    for item in items:
        for out in item.outputs.values() if not item.error else ():
            real = os.path.realpath(out)
            if real in inputs:
                raise ConfigError(f"{item.name}: its output {out} would replace the input {inputs[real]}; "
                                  "write to an output folder that holds no inputs")
            if root is None:
                continue
            first = os.path.relpath(real, root).split(os.sep)[0]
            if first in ("..", ".") or os.path.isabs(first):
                raise ConfigError(f"{item.name}: its output {out} resolves to {real}, outside the output folder "
                                  f"{outdir}")
            if first in (*RESERVED_NAMES, STAGING, LOCK_NAME) or (first.startswith(".stereocli-")
                                                                   and first.endswith(".done")):
                raise ConfigError(f"{item.name}: its output {out} takes the place of {first}, which the batch "
                                  "keeps for itself")


def finished_in_run(item: WorkItem) -> bool:
    """True when ``item``'s outputs were committed by the run ``item.run_id`` (its result may
    have been lost with an interrupted parent or a lost scheduler, its outputs were not)."""
    marker = item.marker
    if not (item.run_id and is_done(item)) or marker is None:
        return False
    try:
        return json.loads(marker.read_text()).get("run") == item.run_id
    except (OSError, ValueError, AttributeError):
        return False


def run_one(item_fn: Callable[[WorkItem], dict], item: WorkItem, verbose_errors: bool) -> ItemResult:
    """Run ``item_fn`` on ``item`` with its outputs staged, then commit them together.

    Any exception becomes a failed outcome with a one-line message naming the item (plus the
    traceback with ``verbose_errors``); nothing of a failed item reaches its final paths.
    Seconds are wall-clock.
    """
    if item.error:
        return ItemResult.failure(item, item.error, item.error_code)
    t0 = time.perf_counter()
    stage: Path | None = None
    dead = 0
    details: dict = {}
    status, message, code = "ok", "", EXIT_OK
    try:
        dead = remove_temporaries(item)  # left by attempts whose process died (killed worker, earlier run)
        stamps = input_stamps(item.inputs)  # the inputs as this attempt reads them, for the marker
        staged, stage = _stage(item)
        details = item_fn(staged) or {}
        if stage is not None:
            _commit(item, stage, stamps)
    except StereoError as exc:
        _reraise_interrupt(exc)
        status, message, code = "failed", str(exc), exc.exit_code
    except MemoryError:
        status, message, code = "failed", "out of memory", EXIT_DATA
    except Exception as exc:  # noqa: BLE001 - one item's bug must not kill the batch
        _reraise_interrupt(exc)
        status, code = "failed", EXIT_DATA
        message = _describe(exc)
        if verbose_errors:
            message += "\n" + traceback.format_exc()
    finally:
        if stage is not None and stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
    if status == "failed":
        details = {}
        if stage is not None:  # name the final folder, not the staging one
            message = message.replace(str(stage), item.folder or str(Path(next(iter(item.outputs.values()))).parent))
        message = label_message(item.name, message)
    return ItemResult(item.name, status, round(time.perf_counter() - t0, 4), message, details,
                      item.inputs, item.outputs, 1 + dead, code)


def _reraise_interrupt(exc: BaseException) -> None:
    """Raise the interrupt hidden in ``exc``: a signal handler that raises while a compiled
    kernel returns surfaces as ``SystemError`` (with the interrupt as its context), and code
    that turns every exception into a message must not turn a Ctrl-C into a failed item."""
    from ..errors import Interrupted
    from ..process import interrupt_received

    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            raise seen from None
        seen = seen.__cause__ or seen.__context__
    signum = interrupt_received()
    if signum is not None:
        raise Interrupted(signum) from None


def _describe(exc: Exception) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return f"{type(exc).__name__}: {exc}"


def label_message(name: str, message: str) -> str:
    """``message`` starting with ``name:`` (every error line names its item)."""
    return message if message.startswith(f"{name}:") else f"{name}: {message}"


# --- staging and committing -------------------------------------------------------------------


def _staging_label(item: WorkItem) -> tuple[Path, str]:
    """The staging root of ``item`` and the prefix of its staging folders."""
    if item.folder:
        folder = Path(item.folder)
        return folder.parent / STAGING, folder.name
    return Path(next(iter(item.outputs.values()))).parent / STAGING, item.name


def _stage(item: WorkItem) -> tuple[WorkItem, Path | None]:
    """``item`` with its outputs redirected into a fresh staging folder (and that folder);
    unchanged when it has no outputs or two outputs share a file name."""
    names = [Path(p).name for p in item.outputs.values()]
    if not names or len(set(names)) != len(names):
        return item, None
    root, label = _staging_label(item)
    root.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f"{label}.", suffix=f".{_run_tag(item)}.stage", dir=root))
    plain_mode(stage, 0o777)  # mkdtemp makes 0700
    return replace(item, outputs={k: str(stage / Path(p).name) for k, p in item.outputs.items()}), stage


def _commit(item: WorkItem, stage: Path, stamps: dict | None = None) -> None:
    """Move the staged outputs of ``item`` into place (signals wait until it is done); ``stamps``
    (:func:`input_stamps`) go into its marker."""
    from ..process import deferred_interrupts

    with deferred_interrupts():
        if item.folder:
            _commit_folder(item, stage, input_stamps(item.inputs) if stamps is None else stamps)
        else:
            for final in item.outputs.values():
                src = stage / Path(final).name
                if src.exists():
                    Path(final).parent.mkdir(parents=True, exist_ok=True)
                    os.replace(src, final)


def _marker_outputs(marker: Path) -> list[str]:
    """The output names a completion marker lists ([] when absent or unreadable)."""
    try:
        names = json.loads(marker.read_text()).get("outputs", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [n for n in names if isinstance(n, str) and "/" not in n and n not in ("", ".", "..")]


def _commit_folder(item: WorkItem, stage: Path, stamps: dict) -> None:
    folder, marker = Path(item.folder), item.marker
    if marker is None:  # (never: only items with a folder are committed here)
        raise ValueError(f"{item.name}: no output folder to commit into")
    written = sorted(p.name for p in stage.iterdir())
    write_text(stage / marker.name, json.dumps({"command": item.command, "outputs": written, "run": item.run_id,
                                                "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                                "version": __version__, "config": item.config_digest,
                                                "inputs": stamps}) + "\n")
    if not os.path.lexists(folder):
        folder.parent.mkdir(parents=True, exist_ok=True)
        os.rename(stage, folder)
        return
    previous = _marker_outputs(marker)
    ours = set(written) | set(previous) | {marker.name}
    if folder.is_dir() and not folder.is_symlink() and set(os.listdir(folder)) <= ours:
        old = stage.with_suffix(".old")
        os.rename(folder, old)
        os.rename(stage, folder)
        shutil.rmtree(old, ignore_errors=True)
        return
    # Shared with other files: replace ours one by one, unmarked until the last rename.
    marker.unlink(missing_ok=True)
    for name in set(previous) - set(written):
        (folder / name).unlink(missing_ok=True)  # an output of the previous run this one does not write
    for name in written:
        os.replace(stage / name, folder / name)
    os.replace(stage / marker.name, marker)


def _run_tag(item: WorkItem) -> str:
    return (item.run_id + "0" * 8)[:8]


def remove_temporaries(item: WorkItem) -> int:
    """Delete what a dead attempt may have left of ``item``: its staging folders, and temporary
    files beside its outputs. Returns how many staging folders of this run (``item.run_id``)
    there were: attempts that died (so ``attempts`` counts Dask's re-runs after a worker died).

    Matches only the names :func:`stereocli.io.atomic.atomic_path` gives the temporaries of
    these outputs (``.<stem>.<8 random chars>.tmp<suffix>``, from :func:`tempfile.mkstemp`) and
    this item's staging folders (``<name>.<8 random>.<8 run id>.stage``, ``.old``), never files
    under final names nor other items' temporaries.
    """
    dead = 0
    for out in item.outputs.values():
        path = Path(out)
        if path.parent.is_dir():
            for tmp in path.parent.glob(f".{glob.escape(path.stem)}.{'?' * 8}.tmp{glob.escape(path.suffix)}"):
                tmp.unlink(missing_ok=True)
    if item.outputs:
        root, label = _staging_label(item)
        if root.is_dir():
            for suffix in ("stage", "old"):
                for leftover in root.glob(f"{glob.escape(label)}.{'?' * 8}.{'?' * 8}.{suffix}"):
                    dead += suffix == "stage" and leftover.name.endswith(f".{_run_tag(item)}.stage")
                    shutil.rmtree(leftover, ignore_errors=True)
    return dead


def remove_staging_roots(items: list[WorkItem]) -> None:
    """Remove the items' staging roots that are left empty."""
    for root in {_staging_label(item)[0] for item in items if item.outputs}:
        try:
            root.rmdir()
        except OSError:
            pass  # absent, or still holds another run's or a dead attempt's folder


def prepare_worker() -> None:
    """Process-wide settings every worker process gets before running items: freed large
    buffers stay in the process between items, and the kernels' start-up settings
    (:mod:`stereocli.process`)."""
    from ..process import keep_freed_memory, prepare_kernels

    keep_freed_memory()
    prepare_kernels()

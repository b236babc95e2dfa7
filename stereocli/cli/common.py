"""CLI plumbing shared by the batch subcommands: reporting results and choosing exit codes."""

from __future__ import annotations

import contextlib
import json
import signal
import sys
from pathlib import Path
from typing import Callable, Sequence

import click

from ..errors import EXIT_DATA
from ..jobs.items import BatchResult, ItemResult, WorkItem, batch_exit_code, stale_reason
from ..runinfo import RunRecord


def unpaired_failures(problems: list[str]) -> list[ItemResult]:
    """Inputs that could not be paired, as failed items (reported, never dropped)."""
    return [ItemResult(name=p.split(":")[0], status="failed", message=p, exit_code=EXIT_DATA) for p in problems]


def run_batch_command(command: str, items: list[WorkItem], item_fn: Callable[[WorkItem], dict], *,
                      outdir: Path | None, config: dict | None, verbosity: int,
                      extra_failures: Sequence[ItemResult] = (), record_extra: Callable[[], dict] | None = None,
                      **batch_options) -> tuple[int, BatchResult]:
    """Run a batch subcommand's items and report: hold ``outdir``'s lock (one run per output
    folder), start the run record, :func:`~stereocli.jobs.executors.run_batch` with
    ``batch_options``, then :func:`finish_batch` into ``outdir/run.json``.
    With ``outdir`` None (a single output file) there is no lock and no run record. Returns the
    exit code and the batch's results. With ``skip_existing``, items whose earlier outputs are
    stale are redone and said so (:func:`~stereocli.jobs.items.stale_reason`). ``record_extra()``
    gives more top-level entries for the run record, asked for once the items have run."""
    from ..jobs.executors import run_batch
    from ..jobs.lock import output_lock
    from ..process import deferred_interrupts

    with output_lock(outdir) if outdir is not None else contextlib.nullcontext():
        record = RunRecord(command, argv(), config)
        redone = {}
        if batch_options.get("skip_existing"):
            redone = {item.name: reason for item in items if (reason := stale_reason(item))}
        result = run_batch(items, item_fn, desc=command, verbose_errors=verbosity >= 2, **batch_options)
        with deferred_interrupts():  # a signal now waits until run.json is written
            if record_extra is not None:
                record.data.update(record_extra())
            code = finish_batch(result, record, None if outdir is None else Path(outdir) / "run.json", verbosity,
                                extra_failures, redone)
    return code, result


def finish_batch(result: BatchResult, record: RunRecord, record_path: Path | None, verbosity: int,
                 extra_failures: Sequence[ItemResult] = (), redone: dict[str, str] | None = None) -> int:
    """Write the run record, report failures on stderr, return the exit code.

    ``redone`` maps the items ``--skip-existing`` ran again to why (their outputs were stale):
    their run-record entries get ``redone``, and stderr a note each.
    0 when every item is ok or skipped; 3 when some items failed; when none succeeded, 2 if
    every failure was a usage/configuration error, else 1; 130/143 when interrupted.
    """
    redone = redone or {}
    items = list(result.results) + list(extra_failures)
    for item in items:
        entry = item.as_dict()
        if item.status != "skipped" and item.name in redone:
            entry["redone"] = redone[item.name]
        record.add_item(entry)
    if result.interrupted:
        record.interrupted(signal.Signals(result.interrupted).name, (result.total or 0) + len(extra_failures))
    if record_path is not None:
        record.write(record_path)
    failed = [i for i in items if i.status == "failed"]
    ok = [i for i in items if i.status == "ok"]
    if verbosity >= 0:
        for item in items:
            if item.status != "skipped" and item.name in redone:
                click.echo(f"Note: {item.name}: stale outputs redone: {redone[item.name]}", err=True)
        for item in ok:
            if verbosity >= 1:
                # What the stages found (e.g. row_align's fit), one line per stage: -v only.
                for stage, note in item.details.get("stage_notes", {}).items():
                    facts = ", ".join(f"{key} {value}" for key, value in note.items())
                    click.echo(f"{item.name}: {stage}: {facts}", err=True)
            for warning in item.details.get("warnings", ()):
                click.echo(f"Warning: {item.name}: {warning}", err=True)
    skipped = [i for i in items if i.status == "skipped"]
    for item in failed:
        click.echo(f"Error: {item.message.splitlines()[0] if item.message else item.name + ': failed'}", err=True)
    if result.interrupted:
        where = f"; run record: {record_path}" if record_path is not None else ""
        click.echo(f"Interrupted ({signal.Signals(result.interrupted).name}): {len(ok)} ok, {len(skipped)} skipped, "
                   f"{len(failed)} failed of {(result.total or 0) + len(extra_failures)}; unfinished items were "
                   f"cancelled and left nothing{where}; --skip-existing resumes", err=True)
        return result.exit_code
    if verbosity >= 0:
        summary = f"{len(ok)} ok, {len(skipped)} skipped, {len(failed)} failed"
        if record_path is not None:
            summary += f"; run record: {record_path}"
        click.echo(summary, err=True)
    return batch_exit_code(items)


def print_json(data) -> None:
    click.echo(json.dumps(data, indent=2, default=str))


def argv() -> list[str]:
    return ["stereocli", *sys.argv[1:]]

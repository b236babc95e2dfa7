"""CLI plumbing shared by the batch subcommands: reporting results and choosing exit codes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from ..errors import EXIT_DATA, EXIT_OK, EXIT_PARTIAL
from ..jobs.items import BatchResult, ItemResult
from ..runinfo import RunRecord


def unpaired_failures(problems: list[str]) -> list[ItemResult]:
    """Inputs that could not be paired, as failed items (reported, never dropped)."""
    return [ItemResult(name=p.split(":")[0], status="failed", message=p) for p in problems]


def finish_batch(result: BatchResult, record: RunRecord, record_path: Path | None, verbosity: int,
                 extra_failures: list[ItemResult] = ()) -> int:
    """Write the run record, report failures on stderr, return the exit code.

    0 when every item is ok or skipped; 1 when nothing succeeded; 3 when some items failed.
    """
    items = list(result.results) + list(extra_failures)
    for item in items:
        record.add_item(item.as_dict())
    if record_path is not None:
        record.write(record_path)
    failed = [i for i in items if i.status == "failed"]
    ok = [i for i in items if i.status == "ok"]
    skipped = [i for i in items if i.status == "skipped"]
    for item in failed:
        click.echo(f"Error: {item.message.splitlines()[0] if item.message else item.name + ': failed'}", err=True)
    if verbosity >= 0:
        summary = f"{len(ok)} ok, {len(skipped)} skipped, {len(failed)} failed"
        if record_path is not None:
            summary += f"; run record: {record_path}"
        click.echo(summary, err=True)
    if not failed:
        return EXIT_OK
    return EXIT_DATA if not ok and not skipped else EXIT_PARTIAL


def print_json(data) -> None:
    click.echo(json.dumps(data, indent=2, default=str))


def argv() -> list[str]:
    return ["stereocli", *sys.argv[1:]]

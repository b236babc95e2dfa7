"""The process-wide allocator setting (stereocli.process): applied by the entry point, not on import."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


def _run(code: str, env_value: str | None = None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "STEREOCLI_KEEP_FREED_MEMORY"}
    if env_value is not None:
        env["STEREOCLI_KEEP_FREED_MEMORY"] = env_value
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          check=True).stdout.strip()


def test_importing_the_library_changes_no_process_setting():
    code = "import stereocli.matching.pipeline, stereocli.jobs, stereocli.process as p; print(p._Allocator.applied)"
    assert _run(code) == "None"


def test_applied_by_the_call_with_glibc_and_disabled_by_the_environment():
    code = "import stereocli.process as p; print(p.keep_freed_memory())"
    if GLIBC:
        assert _run(code) == "True"
    assert _run(code, "0") == "False"


def test_the_command_line_applies_it():
    code = ("import stereocli.process as p; from click.testing import CliRunner; from stereocli.cli.main import cli; "
            "CliRunner().invoke(cli, ['stages', 'census']); print(p._Allocator.applied)")
    assert _run(code) == ("True" if GLIBC else "False")


def test_a_small_budget_keeps_less_here_and_in_the_workers_it_starts():
    code = ("import os, stereocli.process as p; "
            "print(p.keep_freed_memory_within({}), os.environ.get('STEREOCLI_KEEP_FREED_MEMORY'))")
    if GLIBC:
        assert _run(code.format(1.0)) == f"True {2**30 // 256}"  # 1/256 of 1 GiB
        assert _run(code.format(8.0)) == "True None"  # the default budget keeps the default setting
    assert _run(code.format(1.0), "0") == "False 0"  # the user's setting wins

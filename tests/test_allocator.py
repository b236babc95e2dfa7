"""The allocator setting that keeps freed buffers in the process (stereocli.match.allocator)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

CODE = "import stereocli.match.pipeline, stereocli.match.allocator as a; print(a.keep_freed_memory())"


def _applied(env_value: str | None) -> str:
    """What ``keep_freed_memory`` reports in a fresh interpreter after importing the pipeline."""
    env = {k: v for k, v in os.environ.items() if k != "STEREOCLI_KEEP_FREED_MEMORY"}
    if env_value is not None:
        env["STEREOCLI_KEEP_FREED_MEMORY"] = env_value
    return subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, env=env,
                          check=True).stdout.strip()


def test_applied_on_import_with_glibc_and_disabled_by_the_environment():
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert _applied(None) == "True"
    assert _applied("0") == "False"

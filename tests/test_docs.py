"""The documentation describes the tool as it is: generated where it can drift, short where it is read."""

from __future__ import annotations

import importlib.util
import re

import pytest

from conftest import REPO
from stereocli import registry

#: Words that narrate development instead of describing the tool.
DIARY = re.compile(r"\b[Ss]ession [0-9]|\bslow spells?\b|\bthe VM\b|\b[Ii]ssue #?[0-9]+|\brun [A-C]\b|\b[Ww]e tried\b")
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".txt", ".cfg"}


def test_methods_reference_is_generated_from_the_registry():
    # Regenerate with: stereocli stages --format markdown > docs/methods.md
    expected = registry.markdown_reference(registry.stages())
    assert (REPO / "docs" / "methods.md").read_text() == expected


def test_the_reference_documents_every_stage_and_its_traits():
    text = registry.markdown_reference(registry.stages())
    for stage in registry.stages():
        assert f"### `{stage.name}`" in text
    assert "`runs_cost`: when coarse: true" in text  # the SGM's coarse-to-fine search owns the cost stage


def test_readme_is_a_manual_not_a_diary():
    # A user's manual: room to grow, but measurements and design belong in docs/.
    readme = (REPO / "README.md").read_text()
    assert len(readme.encode()) <= 40 * 1024
    for heading in ("## Quick start", "## Architecture", "Choosing a preset"):
        assert heading in readme


def _render_docs():
    spec = importlib.util.spec_from_file_location("render_docs", REPO / "benchmarks" / "render_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_published_scores_are_generated_from_the_scoreboard():
    # Regenerate with: python benchmarks/render_docs.py (from benchmarks/results/scoreboard.json)
    assert _render_docs().stale(REPO) == []


def test_a_scoreboard_block_is_rewritten_and_an_unknown_one_refused():
    render = _render_docs()
    board = render.Board({"runs": {}, "datasets": {}, "methods": {}})
    text = "before\n<!-- scoreboard: v2-bad2 -->\nold table\n<!-- /scoreboard -->\nafter\n"
    assert render.render_text(text, board, yaml=False, where="x.md") == (
        "before\n<!-- scoreboard: v2-bad2 -->\n| scene |\n|---|\n<!-- /scoreboard -->\nafter\n")
    comment = "# scoreboard: preset fast\n# old\n# /scoreboard\nkey: 1\n"
    assert render.render_text(comment, board, yaml=True, where="x.yaml") == (
        "# scoreboard: preset fast\n# Not on the scoreboard yet (benchmarks/results/scoreboard.json).\n"
        "# /scoreboard\nkey: 1\n")
    with pytest.raises(SystemExit, match="x.md: unknown scoreboard block 'nonsense'"):
        render.render_text("<!-- scoreboard: nonsense -->\n<!-- /scoreboard -->\n", board, yaml=False, where="x.md")


def test_readme_quick_start_is_what_ci_runs():
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    commands = [line for line in ci if line.startswith("pip install")]
    readme = (REPO / "README.md").read_text()
    assert len(commands) == 2 and all(c in readme.splitlines() for c in commands)


def test_no_development_history_in_the_project():
    files = [p for p in REPO.rglob("*") if p.is_file() and p.suffix in TEXT_SUFFIXES
             and not {".git", "build", "samples", "__pycache__"} & set(p.relative_to(REPO).parts)
             and ".egg-info" not in str(p) and p.name != "test_docs.py"]
    assert len(files) > 50
    hits = [f"{p.relative_to(REPO)}:{i}: {line.strip()}" for p in files
            for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if DIARY.search(line)]
    assert not hits, "\n".join(hits)

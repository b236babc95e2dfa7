"""``docs/api.md``, the Python API reference, generated from the public functions' docstrings
(numpydoc) as ``docs/methods.md`` is from the stage registry: ``python -m stereocli.apidoc >
docs/api.md`` (``tests/test_api.py`` checks the file is current)."""

from __future__ import annotations

import inspect
import re

__all__ = ["markdown"]

#: The reference's entries, in reading order.
FUNCTIONS = ["match", "read_image", "rectify", "triangulate", "evaluate", "calibrate"]
RESULTS = ["MatchResult", "MatchRange", "RectifyResult", "TriangulationResult", "EvalReport", "CalibrationResult"]
#: Sections rendered as lists of ``name : description`` items.
ITEM_SECTIONS = ("Parameters", "Returns", "Raises", "Attributes")


def _md(text: str) -> str:
    """reStructuredText markup as Markdown: ````x```` and ``:func:`~a.b.x``` become ```x``` (a
    ``~`` keeps the last name only)."""
    text = re.sub(r":(?:func|class|mod|meth|data|attr):`~?([^`]+)`",
                  lambda m: f"`{m.group(1).rsplit('.', 1)[-1] if m.group(0).count('~') else m.group(1)}`", text)
    return re.sub(r"``([^`]+)``", r"`\1`", text)


def _signature(func) -> str:
    """``name(a, b, *, c=None)`` without annotations (they are in the parameter list)."""
    parts, star = [], False
    for p in inspect.signature(func).parameters.values():
        if p.kind is p.KEYWORD_ONLY and not star:
            parts.append("*")
            star = True
        if p.kind is p.VAR_KEYWORD:
            parts.append(f"**{p.name}")
        else:
            parts.append(p.name if p.default is p.empty else f"{p.name}={p.default!r}")
    return f"{func.__name__}({', '.join(parts)})"


def _sections(doc: str) -> tuple[str, list[tuple[str, str]]]:
    """The docstring's text before its first section, and its ``(title, body)`` sections."""
    pieces = re.split(r"^(\w[\w ]*)\n-+\n", doc, flags=re.M)
    return pieces[0].strip(), [(pieces[i], pieces[i + 1].strip("\n")) for i in range(1, len(pieces), 2)]


def _items(body: str) -> list[str]:
    """A numpydoc item list as Markdown bullets: ``- `name` (type): description``."""
    out: list[str] = []
    for line in body.splitlines():
        if not line.strip():
            continue
        if not line.startswith(" "):
            name, _, kind = line.partition(" : ")
            out.append(f"- `{name.strip()}`" + (f" ({kind.strip()})" if kind.strip() else "") + ":")
        elif out:
            out[-1] += " " + line.strip()
    return [item[:-1] if item.endswith(":") else item for item in out]


def _attribute_items(body: str) -> list[str]:
    """``name : description`` lines (a result's attributes) as bullets."""
    out: list[str] = []
    for line in body.splitlines():
        if not line.strip():
            continue
        if not line.startswith(" "):
            name, _, text = line.partition(" : ")
            out.append(f"- `{name.strip()}`: {text.strip()}")
        elif out:
            out[-1] += " " + line.strip()
    return out


def _entry(title: str, obj) -> list[str]:
    doc = inspect.getdoc(obj) or ""
    text, sections = _sections(doc)
    lines = [f"## {title}", "", _md(text), ""]
    for name, body in sections:
        lines += [f"**{name}**", ""]
        if name == "Examples":
            lines += ["```pycon", body, "```"]
        elif name == "Attributes":
            lines += [_md(item) for item in _attribute_items(body)]
        elif name in ITEM_SECTIONS:
            lines += [_md(item) for item in _items(body)]
        else:
            lines.append(_md(body))
        lines.append("")
    return lines


def markdown() -> str:
    """The API reference as Markdown."""
    import stereocli
    from stereocli import api

    intro, _ = _sections(inspect.getdoc(api) or "")
    lines = ["# Python API", "", "Generated from the docstrings by `python -m stereocli.apidoc > docs/api.md`; the "
             "examples run as tests.", "", _md(intro), ""]
    for name in FUNCTIONS:
        lines += _entry(f"`stereocli.{_signature(getattr(stereocli, name))}`", getattr(stereocli, name))
    lines += ["# Results", ""]
    for name in RESULTS:
        lines += _entry(f"`stereocli.{name}`", getattr(stereocli, name))
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(markdown(), end="")

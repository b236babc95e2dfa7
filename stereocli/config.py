"""Configuration files: bundled presets, YAML loading with limits, layering and ``--set``.

A config has one section per pipeline stage plus ``runtime``::

    preprocess:  [{name: none}]               # a stage or a list of stages, run in order
    cost:        {name: census, window: [7, 9]}
    aggregation: [{name: none}]               # a stage or a list
    optimizer:   {name: sgm, paths: 8}
    refinement:  [{name: subpixel}, {name: lr_check, max_diff: 1}]
    runtime:     {memory_gb: 8, strip_rows: 0}

Precedence: the ``default`` preset < ``--config FILE`` < ``--set section.key=value``. When a
higher layer names a different stage for a section, the lower layer's parameters for that
section are dropped (they belonged to the other stage). Lists (``refinement``) are replaced
whole; ``--set refinement.lr_check.max_diff=2`` edits the listed stage of that name,
``--set refinement.lr_check+=confidence`` inserts a stage before it, ``--set refinement+=median``
appends one, ``--set refinement-=median`` removes one and ``--set refinement.median=bilateral``
replaces one (:func:`apply_set`).
This module works on plain dicts; :mod:`stereocli.matching.config` resolves the stages and
validates their parameters.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError, did_you_mean, excerpt

SINGLE_SECTIONS = ("cost", "optimizer")
LIST_SECTIONS = ("preprocess", "aggregation", "refinement")
STAGE_SECTIONS = ("preprocess", "cost", "aggregation", "optimizer", "refinement")
SECTIONS = STAGE_SECTIONS + ("runtime",)


def _suggest(word: str, options) -> str:
    return did_you_mean(word, options) + f"; valid: {', '.join(sorted(map(str, options)))}" if options else ""


# --- presets and files -----------------------------------------------------------------


def preset_dir() -> Path:
    """Folder holding the bundled presets: installed package data, else the checkout's configs/."""
    installed = Path(__file__).resolve().parent / "presets"
    if (installed / "default.yaml").is_file():
        return installed
    return Path(__file__).resolve().parents[1] / "configs"


def preset_names() -> list[str]:
    return sorted(p.stem for p in preset_dir().glob("*.yaml"))


#: A sentence ends at a full stop followed by a word, a backquote or a bracket (not after
#: "et al.", "e.g.", "i.e." or "vs."), or at a colon that opens a list ("...: - item").
_SENTENCE_END = re.compile(r"(?<!\bal)(?<!\be\.g)(?<!\bi\.e)(?<!\bvs)\.(?=\s+[A-Za-z`(])|:(?=\s+- )")


def preset_summary(name: str) -> str:
    """The first sentence of a bundled preset's header comment, whole (for ``config presets``)."""
    lines = []
    for line in (preset_dir() / f"{name}.yaml").read_text().splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if not text or text.startswith("scoreboard:"):
            break
        lines.append(text)
    text = " ".join(lines)
    end = _SENTENCE_END.search(text)
    return text[: end.start()] + "." if end else text


def resolve_config_path(name_or_path: str) -> Path:
    """A path to an existing YAML file, or the name of a bundled preset (``fast``)."""
    path = Path(name_or_path)
    preset = preset_dir() / f"{name_or_path}.yaml"
    try:
        if path.is_file():
            return path
        if not path.suffix and preset.is_file():
            return preset
    except OSError:  # a name too long to be a file's
        pass
    names = preset_names()
    raise ConfigError(
        f"{excerpt(name_or_path)}: no such config file or preset; presets: {', '.join(names)}"
        + did_you_mean(name_or_path, names)
    )


#: Limits on a YAML document (a config is a few dozen lines): its size, its nesting, and the
#: number of values it stands for once aliases are expanded (a "billion laughs" file is tiny
#: but stands for 10^9 strings).
YAML_MAX_BYTES = 256 * 1024
YAML_MAX_DEPTH = 32
YAML_MAX_VALUES = 20_000


def check_yaml_limits(text: str, where: str) -> None:
    """Raise :class:`ConfigError` when ``text`` exceeds :data:`YAML_MAX_BYTES`, nests deeper than
    :data:`YAML_MAX_DEPTH` or expands to more than :data:`YAML_MAX_VALUES` values.

    Works on the parser's event stream (no recursion, nothing expanded), stopping at the first
    event over a limit, so a hostile document fails before it is built.
    """
    if len(text) > YAML_MAX_BYTES:
        raise ConfigError(f"{where}: {len(text)} characters; a config is at most {YAML_MAX_BYTES // 1024} KiB")
    deep = _flow_too_deep(text)
    if deep is not None:
        raise ConfigError(f"{where}: line {deep}: nested deeper than {YAML_MAX_DEPTH} levels; not a config")
    loader_cls = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    loader = loader_cls(text)
    sizes: dict[str, int] = {}  # anchor -> number of values its node stands for
    stack: list[list] = [[None, 0]]  # open collections: [anchor, values so far]
    try:
        while loader.check_event():
            event = loader.get_event()
            if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                stack.append([event.anchor, 0])
                if len(stack) - 1 > YAML_MAX_DEPTH:
                    raise ConfigError(f"{where}: line {event.start_mark.line + 1}: nested deeper than "
                                      f"{YAML_MAX_DEPTH} levels; not a config")
                continue
            if isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                anchor, count = stack.pop()
                count += 1
            elif isinstance(event, yaml.ScalarEvent):
                anchor, count = event.anchor, 1
            elif isinstance(event, yaml.AliasEvent):
                anchor, count = None, sizes.get(event.anchor, 1)
            else:
                continue
            if anchor is not None:
                sizes[anchor] = count
            stack[-1][1] += count
            if stack[-1][1] > YAML_MAX_VALUES:
                raise ConfigError(f"{where}: line {event.start_mark.line + 1}: the document stands for more than "
                                  f"{YAML_MAX_VALUES} values once its aliases are expanded; not a config")
    finally:
        loader.dispose()


def _flow_too_deep(text: str) -> int | None:
    """The line (1-based) where ``[``/``{`` collections first nest deeper than :data:`YAML_MAX_DEPTH`,
    or None; quoted scalars and comments are skipped.

    Checked before the parser runs: on one line, YAML parsers read up to 1 024 characters ahead
    before they report a collection, and libyaml (as PyYAML 6.0.4 bundles it) stops at 1 000
    levels with an error of its own, so the event stream alone would not see this document.
    """
    if text.count("[") + text.count("{") <= YAML_MAX_DEPTH:
        return None
    depth, line, quote, prev, i = 0, 1, "", "\n", 0
    while i < len(text):
        ch = text[i]
        if ch == "\n":
            line += 1
        if quote:
            if ch == "\\" and quote == '"':
                i += 1  # an escaped character, perhaps the quote
            elif ch == quote:
                quote = ""
        elif ch == "#" and prev in " \t\n":
            end = text.find("\n", i)
            i, prev = (len(text) if end < 0 else end), " "
            continue
        elif ch in "'\"" and prev in " \t\n[{,:-":  # a quote opens a scalar only where one may start
            quote = ch
        elif ch in "[{":
            depth += 1
            if depth > YAML_MAX_DEPTH:
                return line
        elif ch in "]}":
            depth = max(0, depth - 1)
        prev = ch
        i += 1
    return None


def safe_yaml(text: str, where: str) -> Any:
    """``yaml.safe_load(text)`` within the limits of :func:`check_yaml_limits`; YAML errors
    (and the limits) raise :class:`ConfigError` naming ``where`` and the line."""
    try:
        check_yaml_limits(text, where)
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{where}:{line} invalid YAML ({excerpt(getattr(exc, 'problem', None) or exc)})") from None
    except RecursionError:
        raise ConfigError(f"{where}: nested too deeply; not a config") from None


def load_yaml(path: Path) -> dict:
    """A config file's mapping (empty for an empty file), loaded within the YAML limits."""
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read(YAML_MAX_BYTES + 1)
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None
    data = safe_yaml(text, str(path))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config must be a mapping of sections ({', '.join(SECTIONS)})")
    return data


# --- merging -------------------------------------------------------------------------------


def _as_stage_list(value: Any, where: str) -> list[dict]:
    if isinstance(value, dict):
        value = [value]
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise ConfigError(f"{where}: expected a stage mapping like {{name: ...}} or a list of them")
    for i, v in enumerate(value):
        if "name" not in v:
            raise ConfigError(f"{where}[{i}]: a stage needs a 'name'")
    return [dict(v) for v in value]


def _merge_stage(lower: dict | None, upper: dict) -> dict:
    if lower is None or upper.get("name", lower.get("name")) != lower.get("name"):
        return dict(upper)
    return {**lower, **upper}


def merge_layer(base: dict, layer: dict, source: str) -> dict:
    """Merge one config layer (a file's contents) over ``base``; returns a new dict."""
    out = copy.deepcopy(base)
    for section, value in layer.items():
        if section not in SECTIONS:
            raise ConfigError(
                f"{source}: {excerpt(section)}: unknown section" + _suggest(str(section), list(SECTIONS))
            )
        where = f"{source}: {section}"
        if section == "runtime":
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: expected a mapping")
            out["runtime"] = {**out.get("runtime", {}), **value}
        elif section in SINGLE_SECTIONS:
            if isinstance(value, list) and len(value) == 1:
                value = value[0]
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: expected one stage mapping like {{name: ...}}")
            if "name" not in value and section not in out:
                raise ConfigError(f"{where}: a stage needs a 'name'")
            out[section] = _merge_stage(out.get(section), value)
        else:
            out[section] = _as_stage_list(value, where)
    return out


#: The forms of ``--set`` (error messages quote them).
SET_FORMS = ("section.key=value, section.<stage name or index>.key=value (listed stages), "
             "section.<stage>=STAGE (replace), section+=STAGE (append), section.<stage>+=STAGE (insert before), "
             "section-=<stage> (remove)")


def parse_set(assignment: str) -> tuple[list[str], str, Any]:
    """Split ``--set`` into its key path, operator (``=``, ``+=`` or ``-=``) and YAML-parsed value.

    ``refinement.lr_check.max_diff=2`` → ``(["refinement", "lr_check", "max_diff"], "=", 2)``;
    ``refinement+=confidence`` → ``(["refinement"], "+=", "confidence")``.
    """
    if "=" not in assignment:
        raise ConfigError(f"--set {excerpt(assignment)}: expected section.key=value; forms: {SET_FORMS}")
    key, raw = assignment.split("=", 1)
    key = key.strip()
    parts, op = split_key(key, f"--set {excerpt(assignment)}", expected="section.key=value (e.g. cost.window=[5,5])")
    if not raw.strip():
        return parts, op, ""
    try:
        check_yaml_limits(raw, f"--set {excerpt(key if op == '=' else key[:-1])}")
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        value = raw
    return parts, op, value


def _stage_entry(value: Any, where: str) -> dict:
    """A stage given on the command line: its name (``confidence``) or a mapping with a name."""
    if isinstance(value, str) and value.strip():
        return {"name": value.strip()}
    if isinstance(value, dict) and "name" in value:
        return dict(value)
    raise ConfigError(f"{where}: expected a stage: its name (e.g. median) or {{name: median, size: 5}}")


def _stage_index(stages_: list[dict], section: str, target: str, where: str, *, example: str,
                 insert: bool = False) -> int:
    """The index of the listed stage ``target`` (a name or an index) in ``stages_``; with
    ``insert`` an index may also be ``len(stages_)`` (the end)."""
    if str(target).isdigit():
        idx = int(target)
        if idx > len(stages_) or (idx == len(stages_) and not insert):
            raise ConfigError(f"{where}: {section} has {len(stages_)} stages (indices 0 to {len(stages_) - 1})")
        return idx
    matches = [i for i, s in enumerate(stages_) if s.get("name") == target]
    if not matches:
        listed = [s.get("name") for s in stages_]
        raise ConfigError(f"{where}: no stage {excerpt(target, quote=True)} in {section}"
                          + _suggest(str(target), listed))
    if len(matches) > 1:
        # E.g. quality's two geodesic_vote stages (rows, columns): editing the first one
        # silently would leave the other as it was.
        at = ", ".join(str(i) for i in matches)
        raise ConfigError(f"{where}: {section} has {len(matches)} {target!r} stages (at {at}); "
                          f"address one by its index, e.g. {example.format(matches[0])}")
    return matches[0]


def apply_set(config: dict, assignment: str) -> dict:
    """Apply one ``--set`` assignment; returns a new dict.

    Forms (:data:`SET_FORMS`): ``section.key=value`` edits a stage or ``runtime``;
    ``section=STAGE`` (a list of them for a listed section) replaces a section; in a listed
    section (``preprocess``, ``aggregation``, ``refinement``) a stage is addressed by name or
    index: ``refinement.median.size=5`` edits it, ``refinement.median=bilateral`` replaces it,
    ``refinement+=STAGE`` appends, ``refinement.lr_check+=confidence`` inserts before it and
    ``refinement-=median`` removes it. STAGE is a name or ``{name: ..., <params>}``.
    """
    parts, op, value = parse_set(assignment)
    return set_value(config, parts, value, f"--set {excerpt(assignment)}", op=op)


def split_key(key: str, where: str, *, expected: str = "section.key (e.g. cost.window)") -> tuple[list[str], str]:
    """``"section.key"`` (``"section.stage.key"``, ``"refinement+"``: :data:`SET_FORMS` without
    the value) as its parts and operator; :class:`ConfigError` naming ``where`` and what was
    ``expected`` when it names no key."""
    key, op = str(key).strip(), "="
    if key.endswith(("+", "-")):
        op, key = key[-1] + "=", key[:-1]
    parts = [p for p in key.split(".") if p]
    if not parts or (op == "=" and len(parts) < 2 and parts[0] not in STAGE_SECTIONS):
        raise ConfigError(f"{where}: expected {expected}; forms: {SET_FORMS}")
    return parts, op


def set_value(config: dict, parts: list[str], value: Any, where: str, op: str = "=") -> dict:
    """Set the key ``parts`` (``["optimizer", "p2"]``, ``["refinement", "lr_check", "max_diff"]``)
    to ``value``, as ``--set`` does with a parsed value, or with ``op`` ``+=``/``-=`` add or
    remove a listed stage (:func:`apply_set`); returns a new dict. Errors name ``where``."""
    section = parts[0]
    if section not in SECTIONS:
        raise ConfigError(f"{where}: unknown section {excerpt(section, quote=True)}"
                          + _suggest(section, list(SECTIONS)))
    out = copy.deepcopy(config)
    if op != "=" and section not in LIST_SECTIONS:
        raise ConfigError(f"{where}: {op} adds or removes a stage of a listed section "
                          f"({', '.join(LIST_SECTIONS)}); set {section} with {section}.key=value")
    if len(parts) == 1 and op == "=":
        # The whole section, as a config file would give it.
        if section in LIST_SECTIONS:
            listed = value if isinstance(value, list) else ([] if value in ("", None) else [value])
            value = [_stage_entry(v, where) for v in listed]
        else:
            value = _stage_entry(value, where)
        return merge_layer(out, {section: value}, where)
    if section in LIST_SECTIONS:
        stages_ = out.setdefault(section, [])
        if op == "+=":
            added = [_stage_entry(v, where) for v in (value if isinstance(value, list) else [value])]
            if len(parts) > 2:
                raise ConfigError(f"{where}: insert with {section}+=STAGE or {section}.<stage name or index>+=STAGE")
            at = len(stages_) if len(parts) == 1 else _stage_index(
                stages_, section, parts[1], where, example=f"{section}.{{}}+={excerpt(added[0]['name'])}", insert=True)
            stages_[at:at] = added
            return out
        if op == "-=":
            if len(parts) != 1 or value in ("", None):
                raise ConfigError(f"{where}: remove with {section}-=<stage name or index>, e.g. {section}-=0")
            del stages_[_stage_index(stages_, section, str(value), where, example=f"{section}-={{}}")]
            return out
        if len(parts) == 2:
            at = _stage_index(stages_, section, parts[1], where, example=f"{section}.{{}}={excerpt(value)}")
            stages_[at] = _stage_entry(value, where)
            return out
        if len(parts) != 3:
            raise ConfigError(f"{where}: address a listed stage as {section}.<stage name or index>.<key>; "
                              f"forms: {SET_FORMS}")
        target, key = parts[1], parts[2]
        entry = stages_[_stage_index(stages_, section, target, where, example=f"{section}.{{}}.{excerpt(key)}")]
        entry[key] = value
        return out
    if len(parts) != 2:
        raise ConfigError(f"{where}: expected {section}.key=value")
    key = parts[1]
    if section == "runtime":
        out.setdefault("runtime", {})[key] = value
    elif key == "name":
        out[section] = {"name": value}
    else:
        out.setdefault(section, {})[key] = value
    return out

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
whole; ``--set refinement.lr_check.max_diff=2`` edits the listed stage of that name.
This module works on plain dicts; :mod:`stereocli.match.config` resolves the stages and
validates their parameters.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError, did_you_mean

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


def resolve_config_path(name_or_path: str) -> Path:
    """A path to an existing YAML file, or the name of a bundled preset (``fast``)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    preset = preset_dir() / f"{name_or_path}.yaml"
    if not path.suffix and preset.is_file():
        return preset
    names = preset_names()
    raise ConfigError(
        f"{name_or_path}: no such config file or preset; presets: {', '.join(names)}"
        + did_you_mean(name_or_path, names)
    )


def load_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{path}:{where} invalid YAML ({getattr(exc, 'problem', exc)})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None
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
                f"{source}: {section}: unknown section" + _suggest(str(section), list(SECTIONS))
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


def parse_set(assignment: str) -> tuple[list[str], Any]:
    """Split ``section.key=value`` into the key path and the YAML-parsed value."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment}: expected section.key=value")
    key, raw = assignment.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if len(parts) < 2:
        raise ConfigError(f"--set {assignment}: expected section.key=value (e.g. cost.window=[5,5])")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return parts, value


def apply_set(config: dict, assignment: str) -> dict:
    """Apply one ``--set`` assignment; returns a new dict."""
    parts, value = parse_set(assignment)
    section = parts[0]
    where = f"--set {assignment}"
    if section not in SECTIONS:
        raise ConfigError(f"{where}: unknown section {section!r}" + _suggest(section, list(SECTIONS)))
    out = copy.deepcopy(config)
    if section in LIST_SECTIONS:
        stages_ = out.setdefault(section, [])
        if len(parts) != 3:
            raise ConfigError(f"{where}: address a listed stage as {section}.<stage name or index>.<key>")
        target, key = parts[1], parts[2]
        if target.isdigit():
            idx = int(target)
            if idx >= len(stages_):
                raise ConfigError(f"{where}: {section} has {len(stages_)} stages")
            entry = stages_[idx]
        else:
            matches = [s for s in stages_ if s.get("name") == target]
            if not matches:
                listed = [s.get("name") for s in stages_]
                raise ConfigError(
                    f"{where}: no stage {target!r} in {section}" + _suggest(target, listed)
                )
            entry = matches[0]
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

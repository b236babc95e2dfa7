"""Matching configuration: YAML presets, ``--set`` overrides, validation, the effective config.

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
Every unknown section, stage or key, wrong type or out-of-range value raises
:class:`ConfigError` naming the file and the key, with the valid choices and close matches.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from . import registry
from .errors import ConfigError
from .registry import Stage, param

SINGLE_SECTIONS = ("cost", "optimizer")
LIST_SECTIONS = ("preprocess", "aggregation", "refinement")
STAGE_SECTIONS = ("preprocess", "cost", "aggregation", "optimizer", "refinement")
SECTIONS = STAGE_SECTIONS + ("runtime",)


@dataclass(frozen=True)
class RuntimeParams:
    """Resources and numerics of a run (not stages)."""

    memory_gb: float = param(8.0, "peak memory budget for one pair; larger jobs run in row strips or are refused", unit="GiB", low=0.1, high=1024)
    strip_rows: int = param(0, "rows per strip (0 = whole image when it fits the budget, else automatic)", unit="rows", low=0, high=100000)
    strip_overlap: int = param(48, "extra rows above and below each strip so paths and windows see context", unit="rows", low=0, high=4096)
    threads: int = param(0, "compiled-kernel threads (0 = all cores); output does not depend on it", low=0, high=1024)


@dataclass
class StageCall:
    """A stage with validated parameters, as it will run."""

    stage: Stage
    params: Any

    def as_dict(self) -> dict:
        return {"name": self.stage.name, **_plain(dataclasses.asdict(self.params))}


@dataclass
class PipelineConfig:
    """The validated effective configuration."""

    preprocess: list[StageCall]
    cost: StageCall
    aggregation: list[StageCall]
    optimizer: StageCall
    refinement: list[StageCall]
    runtime: RuntimeParams = field(default_factory=RuntimeParams)
    sources: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """The effective config with every parameter spelled out (what the run record stores)."""
        return {
            "preprocess": [c.as_dict() for c in self.preprocess],
            "cost": self.cost.as_dict(),
            "aggregation": [c.as_dict() for c in self.aggregation],
            "optimizer": self.optimizer.as_dict(),
            "refinement": [c.as_dict() for c in self.refinement],
            "runtime": _plain(dataclasses.asdict(self.runtime)),
        }

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.as_dict(), sort_keys=False, default_flow_style=None)


def _plain(obj: Any) -> Any:
    """Tuples to lists so YAML/JSON dumps stay plain."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


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
        + registry._close(name_or_path, names)
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
                f"{source}: {section}: unknown section" + registry._suggest(str(section), list(SECTIONS))
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
        raise ConfigError(f"{where}: unknown section {section!r}" + registry._suggest(section, list(SECTIONS)))
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
                    f"{where}: no stage {target!r} in {section}" + registry._suggest(target, listed)
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


# --- validation -----------------------------------------------------------------------------


def _stage_call(kind: str, entry: dict, source: str, section: str) -> StageCall:
    stage = registry.get(kind, str(entry.get("name")), source=source, section=section)
    params = stage.make_params(entry, source=source, section=section)
    return StageCall(stage, params)


def validate(config: dict, source: str = "<config>") -> PipelineConfig:
    """Resolve every stage by name and validate its parameters."""
    for section in ("cost", "optimizer"):
        if section not in config:
            raise ConfigError(f"{source}: missing section {section!r}")
    pre = [_stage_call("preprocess", e, source, f"preprocess.{e.get('name')}") for e in config.get("preprocess", [])]
    cost = _stage_call("cost", config["cost"], source, "cost")
    agg = [_stage_call("aggregation", e, source, f"aggregation.{e.get('name')}") for e in config.get("aggregation", [])]
    opt = _stage_call("optimizer", config["optimizer"], source, "optimizer")
    ref = [_stage_call("refinement", e, source, f"refinement.{e.get('name')}") for e in config.get("refinement", [])]
    seen_map_stage = None
    for call in ref:
        if call.stage.needs_cost and seen_map_stage:
            raise ConfigError(
                f"{source}: refinement: {call.stage.name!r} reads the cost volume and must come before "
                f"{seen_map_stage!r} (stages that only edit the disparity map run after the volume is dropped)"
            )
        if not call.stage.needs_cost:
            seen_map_stage = call.stage.name
    runtime_stage = Stage("runtime", "runtime", lambda *a: None, RuntimeParams, "", "")
    runtime = runtime_stage.make_params(config.get("runtime", {}), source=source, section="runtime")
    return PipelineConfig(pre, cost, agg, opt, ref, runtime)


def build_config(config_files: list[str] | tuple[str, ...] = (), sets: list[str] | tuple[str, ...] = ()) -> PipelineConfig:
    """Defaults < each ``--config`` file in order < each ``--set``; validated.

    Errors name the layer they come from (the file, or the ``--set`` assignment).
    """
    default_path = preset_dir() / "default.yaml"
    merged = merge_layer({}, load_yaml(default_path), str(default_path))
    sources = [str(default_path)]
    for name in config_files:
        path = resolve_config_path(name)
        merged = merge_layer(merged, load_yaml(path), str(path))
        sources.append(str(path))
        # Validate after each file so an error names the file that introduced it.
        validate(merged, str(path))
    for assignment in sets:
        merged = apply_set(merged, assignment)
        validate(merged, f"--set {assignment}")
        sources.append(f"--set {assignment}")
    result = validate(merged, sources[-1])
    result.sources = sources
    return result


def close_matches(word: str, options: list[str]) -> list[str]:
    return difflib.get_close_matches(word, options, n=3, cutoff=0.5)

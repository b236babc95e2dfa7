"""The matcher's validated configuration: every stage resolved by name, parameters checked.

:func:`build_config` layers the ``default`` preset, ``--config`` files and ``--set``
assignments (:mod:`stereocli.config`) and validates the result against the stage registry.
Every unknown stage or key, wrong type or out-of-range value raises :class:`ConfigError`
naming the file and the key, with the valid choices and close matches.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import yaml

from .. import registry
from ..config import apply_set, load_yaml, merge_layer, preset_dir, resolve_config_path, set_value, split_key
from ..errors import ConfigError, excerpt
from ..registry import Stage, param
from . import stages as _stages  # noqa: F401  (registers every built-in stage)


@dataclass(frozen=True)
class RuntimeParams:
    """Resources and numerics of a run (not stages)."""

    memory_gb: float = param(8.0, "peak memory budget for one pair; larger jobs run in row strips or are refused",
                             unit="GiB", low=0.1, high=1024)
    strip_rows: int = param(0, "rows per strip (0 = whole image when it fits the budget, else automatic)",
                            unit="rows", low=0, high=100000)
    strip_overlap: int = param(32, "extra rows above and below each strip so paths and windows see context",
                               unit="rows", low=0, high=4096)
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

    def produces_confidence(self) -> bool:
        """Whether the pipeline makes a confidence map when asked (a refinement whose traits
        say ``produces_confidence``)."""
        return any(call.stage.traits.produces_confidence for call in self.refinement)


def _plain(obj: Any) -> Any:
    """Tuples to lists so YAML/JSON dumps stay plain."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


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
    pre = [_stage_call("preprocess", e, source, f"preprocess.{excerpt(e.get('name'))}")
           for e in config.get("preprocess", [])]
    cost = _stage_call("cost", config["cost"], source, "cost")
    agg = [_stage_call("aggregation", e, source, f"aggregation.{excerpt(e.get('name'))}")
           for e in config.get("aggregation", [])]
    opt = _stage_call("optimizer", config["optimizer"], source, "optimizer")
    ref = [_stage_call("refinement", e, source, f"refinement.{excerpt(e.get('name'))}")
           for e in config.get("refinement", [])]
    seen_map_stage = None
    for call in ref:
        if call.stage.traits.needs_cost and seen_map_stage:
            raise ConfigError(
                f"{source}: refinement: {call.stage.name!r} reads the cost volume and must come before "
                f"{seen_map_stage!r} (stages that only edit the disparity map run after the volume is dropped); "
                f"e.g. --set refinement.{first_map_stage(ref)}+={call.stage.name} inserts it before the first of them"
            )
        if not call.stage.traits.needs_cost:
            seen_map_stage = call.stage.name
    runtime_stage = Stage("runtime", "runtime", lambda *a: None, RuntimeParams, "", "")
    runtime = runtime_stage.make_params(config.get("runtime", {}), source=source, section="runtime")
    return PipelineConfig(pre, cost, agg, opt, ref, runtime)


def first_map_stage(refinement: list[StageCall]) -> str:
    """How ``--set`` addresses the first refinement that only edits the map (not ``needs_cost``):
    its name, or its index when the name is listed twice; the list's length when there is none
    (inserting there appends)."""
    names = [c.stage.name for c in refinement]
    for i, call in enumerate(refinement):
        if not call.stage.traits.needs_cost:
            return call.stage.name if names.count(call.stage.name) == 1 else str(i)
    return str(len(refinement))


def confidence_hint(config: PipelineConfig) -> str:
    """The ``--set`` that adds a ``confidence`` stage to ``config``: before the first stage that
    only edits the map (the stage reads the cost volume)."""
    target = first_map_stage(config.refinement)
    where = "refinement+=" if target == str(len(config.refinement)) else f"refinement.{target}+="
    return f"--set {where}confidence"


def build_config(config_files: Sequence[str | os.PathLike | Mapping] = (), sets: Sequence[str] = (), *,
                 values: Mapping[str, Any] | None = None) -> PipelineConfig:
    """Defaults < each ``--config`` file in order < each ``--set`` < each of ``values``; validated.

    ``config_files``: preset names (``fast``) or YAML paths, or mappings laid over like a file's
    contents; ``sets``: ``section.key=value`` assignments (the value is YAML); ``values``:
    ``{"section.key": value}`` with Python values (``{"optimizer.p2": 1.2}``). Errors name the
    layer they come from (the file, or the ``--set`` assignment).
    """
    default_path = preset_dir() / "default.yaml"
    merged = merge_layer({}, load_yaml(default_path), str(default_path))
    sources = [str(default_path)]
    for layer in config_files:
        if isinstance(layer, Mapping):
            source, contents = "<mapping>", dict(layer)
        else:
            path = resolve_config_path(str(layer))
            source, contents = str(path), load_yaml(path)
        merged = merge_layer(merged, contents, source)
        sources.append(source)
        # Validate after each file so an error names the file that introduced it.
        validate(merged, source)
    for assignment in sets:
        merged = apply_set(merged, assignment)
        validate(merged, f"--set {excerpt(assignment)}")
        sources.append(f"--set {assignment}")
    for key, value in (values or {}).items():
        where = f"set {excerpt(key)}={excerpt(value, quote=True)}"
        parts, op = split_key(key, where)
        merged = set_value(merged, parts, copy.deepcopy(value), where, op=op)
        validate(merged, where)
        sources.append(where)
    result = validate(merged, excerpt(sources[-1]))
    result.sources = sources
    return result


def small_twin(config: PipelineConfig, height: int, width: int, ndisp: int) -> PipelineConfig:
    """``config`` for a tiny warm-up pair that runs the kernels a ``height`` × ``width`` pair
    with ``ndisp`` disparities runs: every stage's params pass through its ``small_twin``
    trait (stages whose code path does not depend on the size keep theirs)."""

    def twin(call: StageCall) -> StageCall:
        make = call.stage.traits.small_twin
        return call if make is None else StageCall(call.stage, make(call.params, height, width, ndisp))

    return dataclasses.replace(config, preprocess=[twin(c) for c in config.preprocess], cost=twin(config.cost),
                               aggregation=[twin(c) for c in config.aggregation], optimizer=twin(config.optimizer),
                               refinement=[twin(c) for c in config.refinement])

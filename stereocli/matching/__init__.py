"""Matching: the Scharstein-Szeliski pipeline (preprocess -> cost -> aggregation -> optimizer ->
refinement), each stage a registered, validated, swappable component. See :mod:`.pipeline`."""

#: Public name -> the submodule that defines it (imported on first use: importing a stage module
#: registers its stages, and only the stages a config names are loaded).
_EXPORTS = {
    "PipelineConfig": "config", "build_config": "config", "validate": "config",
    "match_pair": "pipeline", "prepare": "pipeline", "run_strip": "pipeline", "run_strips": "pipeline",
    "finish": "pipeline", "estimate_memory": "pipeline", "plan_strips": "pipeline",
    "MatchState": "state",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

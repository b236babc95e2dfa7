"""Matching: the Scharstein-Szeliski pipeline (preprocess -> cost -> aggregation -> optimizer ->
refinement), each stage a registered, validated, swappable component. See :mod:`.pipeline`."""

from ..lazy import lazy_exports

#: Public name -> the submodule that defines it (imported on first use: importing a stage module
#: registers its stages, and only the stages a config names are loaded).
_EXPORTS = {
    "PipelineConfig": ".config", "build_config": ".config", "validate": ".config",
    "match_pair": ".pipeline", "prepare": ".pipeline", "run_strip": ".pipeline", "run_strips": ".pipeline",
    "finish": ".pipeline", "estimate_memory": ".pipeline", "plan_strips": ".pipeline",
    "MatchState": ".state",
}
__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

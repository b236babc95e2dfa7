"""Matching: the Scharstein-Szeliski pipeline (preprocess -> cost -> aggregation -> optimizer ->
refinement), each stage a registered, validated, swappable component. See :mod:`.pipeline`."""

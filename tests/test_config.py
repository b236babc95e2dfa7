"""Registry and configuration: validation errors name the file, key, choices and close matches."""

from __future__ import annotations

import pytest

from stereocli import registry
from stereocli.config import parse_set
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config


def test_every_stage_has_summary_and_documented_params():
    for stage in registry.stages():
        assert stage.summary, f"{stage.kind}.{stage.name} has no docstring"
        for spec in stage.param_specs():
            assert spec.help, f"{stage.kind}.{stage.name}.{spec.name} has no help"


def test_default_preset_validates_and_round_trips(tmp_path):
    cfg = build_config()
    dumped = tmp_path / "effective.yaml"
    dumped.write_text(cfg.to_yaml())
    again = build_config([str(dumped)])
    assert again.as_dict() == cfg.as_dict()


def test_precedence_defaults_file_set(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("cost: {name: census, window: [5, 5]}\n")
    assert build_config([str(f)]).cost.params.window == (5, 5)
    assert build_config([str(f)], ["cost.window=[3,3]"]).cost.params.window == (3, 3)


def test_changing_stage_name_drops_old_params(tmp_path):
    cfg = build_config(sets=["cost.name=ad"])
    assert cfg.cost.stage.name == "ad"


def test_set_edits_listed_stage_by_name():
    cfg = build_config(sets=["refinement.lr_check.max_diff=2.5"])
    [lr] = [c for c in cfg.refinement if c.stage.name == "lr_check"]
    assert lr.params.max_diff == 2.5


@pytest.mark.parametrize(
    "content, expected",
    [
        ("cost: {name: censsus}\n", ["cost.name", "censsus", "did you mean 'census'"]),
        ("cost: {name: census, windw: [7, 9]}\n", ["cost.windw", "did you mean 'window'", "valid: gamma_c, window"]),
        ("cost: {name: census, window: seven}\n", ["cost.window", "expected a pair"]),
        ("refinement: [{name: median, size: 99}]\n", ["median", "size", "out of range"]),
        ("refinement: [{name: subpixel, method: cubic}]\n", ["method", "'cubic' is not one of", "parabola"]),
        ("optimiser: {name: wta}\n", ["optimiser", "unknown section", "did you mean 'optimizer'"]),
        ("cost: [1, 2\n", ["invalid YAML"]),
    ],
)
def test_config_errors_name_file_and_key(tmp_path, content, expected):
    f = tmp_path / "bad.yaml"
    f.write_text(content)
    with pytest.raises(ConfigError) as info:
        build_config([str(f)])
    message = str(info.value)
    assert str(f) in message
    for part in expected:
        assert part in message


def test_set_names_a_stage_listed_twice_by_its_index():
    # quality votes along rows (refinement 8), then along columns (9), in two geodesic_vote stages.
    with pytest.raises(ConfigError, match=r"refinement has 2 'geodesic_vote' stages \(at 8, 9\); address one by its "
                                          r"index, e.g. refinement.8.gamma_s"):
        build_config(["quality"], ["refinement.geodesic_vote.gamma_s=50"])
    cfg = build_config(["quality"], ["refinement.9.gamma_s=50"])
    rows, columns = [c.params for c in cfg.refinement if c.stage.name == "geodesic_vote"]
    assert (rows.lines, rows.gamma_s, columns.lines, columns.gamma_s) == ("rows", 25.0, "columns", 50.0)


def test_set_errors():
    with pytest.raises(ConfigError, match="expected section.key=value"):
        parse_set("costwindow")
    with pytest.raises(ConfigError, match="no stage 'lr_chek'.*did you mean 'lr_check'"):
        build_config(sets=["refinement.lr_chek.max_diff=2"])
    with pytest.raises(ConfigError, match="expected true or false|expected a number"):
        build_config(sets=["refinement.lr_check.max_diff=yes"])


def test_unknown_preset_lists_presets():
    with pytest.raises(ConfigError, match="presets: .*default.*fast"):
        build_config(["fsat"])


def test_bundled_presets_validate():
    from stereocli.config import preset_names

    names = preset_names()
    assert {"default", "fast"} <= set(names)
    for name in names:
        build_config([name])


def test_registry_lookup_errors_and_listing():
    assert "census" in registry.names("cost")
    assert registry.names("cost", "cen*") == ["census"] or "census" in registry.names("cost", "cen*")
    with pytest.raises(ConfigError, match="unknown cost stage 'censos'.*did you mean 'census'"):
        registry.get("cost", "censos")


def test_duplicate_registration_is_an_error():
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class P:
        pass

    @registry.register("aggregation", "dup_test", P)
    def first(state, p):
        """First."""

    try:
        with pytest.raises(ValueError, match="registered twice"):
            registry.register("aggregation", "dup_test", P)(first)
    finally:
        registry._unregister("aggregation", "dup_test")


@pytest.mark.parametrize("config, produces", [
    (["fast"], False),
    (["default"], True),  # its confidence stage
    ([{"refinement": [{"name": "local_consistency", "radius": 4}]}], True),
    ([{"refinement": [{"name": "median", "size": 3}]}], False),
])
def test_the_confidence_trait_says_what_a_match_makes(config, produces):
    # match --confidence asks the config (its stages' traits) before any work; a match of a tiny
    # pair that wants the map shows the traits tell the truth.
    import numpy as np

    from stereocli.matching.warmup import tiny_match

    cfg = build_config(config)
    assert cfg.produces_confidence() is produces
    result = tiny_match(cfg, channels=3, dtype=np.dtype(np.uint8), min_disp=0, ndisp=16, masks=False,
                        want_confidence=True)
    assert (result.confidence is not None) is produces

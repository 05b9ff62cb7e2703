"""The gateway's copy of the stage settings is the pipeline's, and it checks names and kinds
as the worker's `replace_section` does."""

from __future__ import annotations

import pytest

from app.core.stage_settings import check_settings, stage_settings
from pipeline.stage_config import ReconstructConfig, config_from_options, settings_kinds


def test_the_gateways_copy_is_the_pipelines() -> None:
    assert stage_settings() == settings_kinds(), "run `make stage-settings` and commit the file"


@pytest.mark.parametrize("section, values", [
    ("enhancement", {"method": "regressor", "views": 14, "strength": 1}),
    ("enhancement", {"self_check": True}),
    ("meshing", {"poisson_depth": 7}),
    ("colorize", {"fallback_rgb": [1, 2, 3]}),
])
def test_what_the_gateway_accepts_the_worker_accepts(section: str, values: dict) -> None:
    check_settings(section, values)
    config = config_from_options({section: values})
    assert config != ReconstructConfig()


@pytest.mark.parametrize("section, values, named", [
    ("enhancement", {"bogus": 1}, "enhancement.bogus"),
    ("enhancement", {"views": True}, "enhancement.views"),
    ("enhancement", {"strength": "high"}, "enhancement.strength"),
    ("enhancement", {"update": 1}, "enhancement.update"),
    ("enhancement", {"self_check": "yes"}, "enhancement.self_check"),
    ("remesh", {"target_edge_length_m": [0.01]}, "remesh.target_edge_length_m"),
])
def test_what_the_gateway_refuses_the_worker_refuses_by_the_same_name(
        section: str, values: dict, named: str) -> None:
    with pytest.raises(ValueError, match=named.replace(".", r"\.")):
        check_settings(section, values)
    with pytest.raises(ValueError, match=named.replace(".", r"\.")):
        config_from_options({section: values})


@pytest.mark.parametrize("setting, replaced_by", [
    ("presmooth_adaptive", "scale selection"),
    ("correction_gain", "gain network"),
    ("ensemble", "corrected once"),
    ("iterations", "classical"),
])
def test_a_removed_setting_is_refused_naming_what_replaced_it(setting: str,
                                                               replaced_by: str) -> None:
    pattern = rf"enhancement\.{setting}: removed; .*{replaced_by}"
    with pytest.raises(ValueError, match=pattern):
        check_settings("enhancement", {setting: 1})
    with pytest.raises(ValueError, match=pattern):
        config_from_options({"enhancement": {setting: 1}})


def test_an_unknown_setting_lists_only_what_can_be_set() -> None:
    with pytest.raises(ValueError) as refused:
        check_settings("enhancement", {"bogus": 1})
    known = str(refused.value).split("known: ")[1]
    assert "method" in known
    assert "presmooth_adaptive" not in known and "update" not in known

"""Stage output keys: a setting invalidates its own stage and the later ones, never earlier."""

from __future__ import annotations

import dataclasses

from pipeline.stage_config import ReconstructConfig, config_from_options
from pipeline.stages import SECTION_FIRST_STAGE, STAGES
from workers.plan import plan_stages, stage_keys


def keys(**options: object) -> list[str]:
    return stage_keys(STAGES, config_from_options(options))


def test_every_config_section_is_mapped_to_a_pipeline_stage() -> None:
    # An unmapped section is safe (counted as read by every stage) but loses reuse.
    fields = dataclasses.asdict(ReconstructConfig())
    sections = {name for name, value in fields.items() if isinstance(value, dict)}
    assert sections <= set(SECTION_FIRST_STAGE) <= set(fields)
    assert set(SECTION_FIRST_STAGE.values()) <= set(STAGES)


def test_keys_are_stable_and_distinct() -> None:
    assert keys() == keys()
    assert len(set(keys())) == len(STAGES)


def test_a_late_setting_keeps_the_early_outputs() -> None:
    base = keys()
    changed = keys(remesh={"iterations": 1}, colorize={})
    at = STAGES.index("remesh")
    assert changed[:at] == base[:at]
    assert all(a != b for a, b in zip(changed[at:], base[at:], strict=True))


def test_a_setting_changes_its_stage_and_later_ones() -> None:
    base = keys()
    for options in ({"depth_filter": {"max_depth_m": 4.0}}, {"frame_index": 3},
                    {"target_edge_length_m": 0.05, "meshing": {"poisson_depth": 7}}):
        changed = keys(**options)
        first = 0 if "meshing" not in options else STAGES.index("mesh")
        assert changed[:first] == base[:first], options
        assert all(a != b for a, b in zip(changed[first:], base[first:], strict=True)), options


def test_plans_end_with_export_and_drop_enhance_when_off() -> None:
    assert plan_stages({"enhance": False})[-1] == "export"
    assert "enhance" not in plan_stages({"enhance": False})
    assert plan_stages({}) == plan_stages({"enhance": False})
    assert plan_stages({"enhance": True})[:-1] == list(STAGES)
    assert plan_stages({"calibration_capture_id": "c" * 32})[0] == "calibrate"
    assert plan_stages({"calibration_capture_id": "c" * 32, "calibrate_only": True}) == \
        ["calibrate"]


def test_turning_enhancement_on_keeps_the_stages_before_it() -> None:
    off = plan_stages({})[:-1]
    on = plan_stages({"enhance": True})[:-1]
    off_keys = stage_keys(tuple(off), config_from_options({}))
    on_keys = stage_keys(tuple(on), config_from_options({"enhance": True}))
    at = on.index("enhance")
    assert on_keys[:at] == off_keys[:at]
    assert on_keys[at + 1] != off_keys[at]  # colorize comes after the moved vertices


def test_the_api_offers_every_config_section() -> None:
    from app.schemas import JobCreate

    sections = {name for name, value in dataclasses.asdict(ReconstructConfig()).items()
                if isinstance(value, dict)}
    assert sections <= set(JobCreate.model_fields)


def test_a_worker_keeps_its_enhance_networks_between_jobs(tmp_path) -> None:
    """The same networks for every config they fit (another sampling setting too); a
    config that needs others loads them in their place."""
    from pipeline.enhance.config import EnhanceConfig
    from workers.context import WorkerContext
    from workers.settings import Settings

    ctx = WorkerContext.create(Settings(data_dir=tmp_path))
    config = EnhanceConfig(method="regressor", device="cpu")
    first = ctx.enhance_networks(config)
    assert ctx.enhance_networks(config) is first
    assert ctx.enhance_networks(dataclasses.replace(config, resolution=128)) is first
    other = ctx.enhance_networks(dataclasses.replace(config, method="classical"))
    assert other is not first and other.gain is None and ctx.networks is other

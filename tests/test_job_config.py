"""The job config (services/jobconfig.py): one typed model whose types, choices and bounds come from the core's
dataclasses and RANGES, so the service refuses at creation what the pipeline would fail on later; and the core's
own checks (`TTOConfig.check`, `ExtractConfig.check`) use the same ranges."""

from __future__ import annotations

from dataclasses import replace

import pytest
from pydantic import ValidationError

from neumatex_core.config import Range
from neumatex_core.pipeline import RANGES, ExtractConfig
from neumatex_core.tto.config import RANGES as TTO_RANGES
from neumatex_core.tto.config import TTOConfig
from services.jobconfig import JobConfig, build_config


def test_schema_bounds_are_the_core_ranges() -> None:
    schema = JobConfig.model_json_schema()
    for props, ranges in ((schema["properties"], RANGES), (schema["$defs"]["TTOOverrides"]["properties"],
                                                           TTO_RANGES)):  # fmt: skip
        for name, allowed in ranges.items():
            if name not in props:  # tto.seed: set by the top-level seed
                continue
            bounds = props[name]["anyOf"][0]
            assert bounds["maximum"] == allowed.hi, name
            assert bounds["exclusiveMinimum" if allowed.lo_open else "minimum"] == allowed.lo, name
    assert schema["properties"]["device"]["anyOf"][0]["enum"] == ["auto", "cpu", "cuda"]
    assert schema["properties"]["variation"]["anyOf"][0]["enum"] == ["textured", "uniform", "choose"]
    assert "lmrm_weights" not in schema["properties"] and "lmrm_readout" not in schema["properties"]
    assert "init" not in schema["$defs"]["TTOOverrides"]["properties"]


@pytest.mark.parametrize("overrides, words", [
    ({"tto": {"steps": 2.5}}, "tto.steps"),
    ({"tto": {"steps": True}}, "tto.steps"),
    ({"tto": []}, "tto"),
    ({"view_resolution": 0}, "greater than or equal to 16"),
    ({"view_resolution": -8}, "greater than or equal to 16"),
    ({"tto": {"lr_final": 1.5}}, "less than or equal to 1"),
    ({"device": "cuda:1"}, "device"),
    ({"preset_name": "gpu"}, "preset_name"),
    ({"tto": {"reg": "oracle"}}, "evaluation variant"),
    ({"tto": {"material": "pbr"}}, "PBR baseline"),
    ({"init": "pbr", "tto": {"field": "uv"}}, "init='pbr'"),
    ({"variation": "striped"}, "variation"),
    ({"init": "random", "variation": "uniform"}, "variation='uniform'"),
    ({"tto": {"select_uniform": True, "lambda_consistency": 0}}, "select_uniform"),
    ({"tto": {"alternative_basis": "nmx-basis-v9"}}, "alternative_basis='nmx-basis-v9' is not installed"),
    ({"tto": {"alternative_basis": "nmx-basis-v5-783ebde8beb7"}}, "has 12 latent numbers: only a triplane field"),
])  # fmt: skip
def test_bad_configs_are_refused_before_the_job(overrides: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(".", r"\.")):
        build_config("tiny", overrides)


def test_good_config_builds_the_pipeline_config() -> None:
    cfg = build_config("tiny", {"name": "red teapot", "init": "random", "device": "cpu", "seed": 3,
                                "tto": {"steps": 5, "lr": 1}})  # fmt: skip
    assert cfg.name == "red teapot" and cfg.tto.steps == 5 and cfg.tto.lr == 1.0 and cfg.tto_config().seed == 3
    assert build_config("cpu", {"tto": None}) == ExtractConfig.preset("cpu")
    assert build_config("cpu", {"variation": "choose"}).tto_config().select_uniform
    with pytest.raises(ValueError, match="unknown preset"):
        build_config("huge", {})
    with pytest.raises(ValidationError):
        JobConfig.model_validate({"stepz": 1})


def test_core_checks_use_the_same_ranges() -> None:
    assert ExtractConfig.preset("tiny", name="x").name == "x"  # `name` no longer clashes with preset()'s argument
    for name in ("tiny", "cpu", "gpu"):
        ExtractConfig.preset(name).check()
    with pytest.raises(ValueError, match="TTO steps must be >= 1 and <= 100000, got 0"):
        replace(TTOConfig(), steps=0).check()
    with pytest.raises(ValueError, match="TTO lr must be > 0"):
        replace(TTOConfig(), lr=0.0).check()
    with pytest.raises(ValueError, match="config view_resolution must be >= 16"):
        ExtractConfig.preset("tiny", view_resolution=8).check()
    assert 1 in Range(0, 1, lo_open=True) and 0 not in Range(0, 1, lo_open=True) and True not in Range(0, 2)

"""Job configuration: a preset ("tiny", "cpu", "gpu") plus overrides of ExtractConfig fields, with TTO fields under
"tto". Checked completely when the job is created, so a bad config is a 422 and never a failed job.

`JobConfig` is one typed model (shown in OpenAPI) generated from the core's dataclasses, so each rule is written
once, in the core: a field's type and choices come from its annotation (`Literal[...]`), its bounds from the
core's RANGES (`neumatex_core.pipeline.RANGES`, `neumatex_core.tto.config.RANGES`). Integers are strict (2.5 or
"3" is refused, not rounded), an object is needed where one is expected (`"tto": []` is refused) and unknown keys
are refused. `build_config` then applies the core's own `ExtractConfig.check` (cross-field rules, and the
evaluation-only TTO variants that make no asset: reg "oracle", material "pbr"). Workers build the same config from
the stored overrides.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictInt, StrictStr, create_model

from neumatex_core.config import Range
from neumatex_core.pipeline import PRESETS, RANGES, ExtractConfig
from neumatex_core.tto.config import RANGES as TTO_RANGES
from neumatex_core.tto.config import TTOConfig

NOT_OVERRIDABLE = {"preset_name", "lmrm_weights", "lmrm_readout", "tto"}  # server paths; tto: nested
TTO_FROM_TOP = {"init", "seed"}  # the top-level init and seed set these (ExtractConfig.tto_config)
NAME_MAX = 200
STRICT: dict[Any, Any] = {int: StrictInt, bool: StrictBool, str: StrictStr}

if TYPE_CHECKING:
    PresetName = str
else:
    PresetName = Literal[PRESETS]


def _bounds(allowed: Range | None) -> dict[str, float]:
    if allowed is None:
        return {}
    return {"gt" if allowed.lo_open else "ge": allowed.lo, "le": allowed.hi}


def _overrides(model: str, cls: type, ranges: dict[str, Range], skip: set[str], doc: str,
               **more: Any) -> type[BaseModel]:
    """A pydantic model with one optional field per field of the dataclass `cls` (None: the preset's value)."""
    hints = typing.get_type_hints(cls)
    spec: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        hint = hints[f.name]
        kw: dict[str, Any] = {**_bounds(ranges.get(f.name)), **({"max_length": NAME_MAX} if hint is str else {})}
        spec[f.name] = (typing.Optional[STRICT.get(hint, hint)], Field(None, **kw))  # noqa: UP045 - runtime type
    return create_model(model, __config__=ConfigDict(extra="forbid", strict=True), __doc__=doc, **spec, **more)


if TYPE_CHECKING:

    class TTOOverrides(BaseModel):
        pass

    class JobConfig(BaseModel):
        tto: TTOOverrides | None = None
else:
    TTOOverrides = _overrides("TTOOverrides", TTOConfig, TTO_RANGES, TTO_FROM_TOP,
                              "TTO fields (neumatex_core.tto.config.TTOConfig); unset: the preset's value")
    JobConfig = _overrides("JobConfig", ExtractConfig, RANGES, NOT_OVERRIDABLE,
                           "ExtractConfig field overrides (neumatex_core.pipeline.ExtractConfig); unset: the preset's "
                           "value", tto=(typing.Optional[TTOOverrides], Field(None)))  # noqa: UP045


def given(config: JobConfig) -> dict[str, Any]:
    """The overrides as stored in the job record (fields left unset or null are the preset's)."""
    return config.model_dump(exclude_none=True)


def build_config(preset: str, overrides: dict[str, Any] | JobConfig) -> ExtractConfig:
    """The pipeline's config; ValueError in plain words for an unknown preset, field or bad value."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r} (expected one of {', '.join(PRESETS)})")
    model = overrides if isinstance(overrides, BaseModel) else JobConfig.model_validate(overrides)
    top = given(model)
    tto = top.pop("tto", None) or {}
    cfg = ExtractConfig.preset(preset, **top)
    cfg = replace(cfg, tto=replace(cfg.tto, **tto))
    cfg.check()
    return cfg

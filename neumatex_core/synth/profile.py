"""Where a synthetic object's time goes: ray queries, material field and evaluation, image writing, the rest.

`StageTimes` accumulates wall-clock seconds per stage. `TimedRayCaster` wraps a RayCaster (closest hits and
shadow rays count as "rays"); `TimedField` wraps a MaterialField so that the field query (region noise, colour
pattern: "field") and every eval / sample / pdf / albedo of the materials it returns ("material": the neural
basis MLPs) are timed. The writer times image and file writing itself ("write"). On CPU torch runs
synchronously, so wall-clock spans are the work done on an idle machine; each span also records the process's CPU
seconds (`time.process_time`), which other processes competing for the cores do not inflate (a synthesis worker
runs one torch thread, so its CPU seconds are its work).
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from neumatex_core.geometry.raycast import Hits, RayCaster
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.base import Material
from neumatex_core.materials.field import MaterialField


class StageTimes:
    """Wall-clock seconds (`seconds`) and process CPU seconds (`cpu`) per stage name."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start
            self.cpu[name] += time.process_time() - cpu

    def as_dict(self) -> dict[str, float]:
        """Wall-clock seconds per stage, rounded to 0.1 ms."""
        return {k: round(v, 4) for k, v in sorted(self.seconds.items())}

    def cpu_dict(self) -> dict[str, float]:
        """CPU seconds per stage, rounded to 0.1 ms."""
        return {k: round(v, 4) for k, v in sorted(self.cpu.items())}


class TimedRayCaster(RayCaster):
    """A RayCaster whose queries are timed as "rays" (wraps another one; builds no BVH of its own)."""

    def __init__(self, inner: RayCaster, times: StageTimes) -> None:
        self.inner, self.times, self.mesh = inner, times, inner.mesh

    def intersect(self, origins: torch.Tensor, directions: torch.Tensor) -> Hits:
        with self.times.stage("rays"):
            return self.inner.intersect(origins, directions)

    def occluded(self, origins: torch.Tensor, directions: torch.Tensor, t_max: torch.Tensor | None = None
                 ) -> torch.Tensor:
        with self.times.stage("rays"):
            return self.inner.occluded(origins, directions, t_max)


class TimedMaterial(Material):
    """A Material whose queries are timed as "material"."""

    def __init__(self, inner: Material, times: StageTimes) -> None:
        self.inner, self.times = inner, times

    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        with self.times.stage("material"):
            return self.inner.eval(wi, wo)

    def sample(self, wo: torch.Tensor, u_lobe: torch.Tensor, u_dir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with self.times.stage("material"):
            return self.inner.sample(wo, u_lobe, u_dir)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        with self.times.stage("material"):
            return self.inner.pdf(wi, wo)

    def albedo(self, wo: torch.Tensor) -> torch.Tensor:
        with self.times.stage("material"):
            return self.inner.albedo(wo)

    def select(self, index: torch.Tensor) -> Material:
        return TimedMaterial(self.inner.select(index), self.times)


class TimedField(MaterialField):
    """A MaterialField whose queries are timed as "field" and whose materials as "material"."""

    def __init__(self, inner: MaterialField, times: StageTimes) -> None:
        self.inner, self.times = inner, times

    def at(self, si: SurfaceInteraction) -> Material:
        with self.times.stage("field"):
            return TimedMaterial(self.inner.at(si), self.times)

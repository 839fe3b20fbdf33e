"""`SynthConfig`: the options of `neumatex synth` (and of `synth.dataset.generate`).

Fields in CONTENT_FIELDS decide what the files contain; they are recorded in the output folder's `synth.json`
and the manifest, and a resumed run must use the same ones. The others (where, how many at once, which shard)
change nothing in the files.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from neumatex_core.config import option, parse_shard

CONTENT_FIELDS = ("split", "seed", "resolution", "spp", "max_bounces", "photos", "relight_maps", "relight_spp",
                  "layered")  # fmt: skip


def default_shared() -> Path:
    """The shared data folder: $NEUMATEX_SHARED/data, else ../shared/data beside the repository."""
    env = os.environ.get("NEUMATEX_SHARED")
    if env:
        return Path(env) / "data"
    return Path(__file__).resolve().parents[3] / "shared" / "data"


@dataclass
class SynthConfig:
    """`neumatex synth`: synthetic objects with known neural materials, each a capture folder (23 preset views as
    linear EXR + tonemapped PNG, masks, ground-truth G-buffers; extra photos at random poses; held-out lighting),
    plus manifest.json. Deterministic by seed, resumable, parallel over processes, sharded."""

    n: int = option(100, "number of objects (indices 0..n-1 of the split)")
    out: str = option("data/synth-train", "output folder")
    split: Literal["train", "test"] = option("train", "train, or test: the benchmark (held-out meshes and seeds)")
    seed: int = option(0, "dataset seed: object i of a split depends only on (split, i, seed)")
    resolution: int = option(128, "image size of every view (pixels, square)")
    spp: int = option(32, "samples per pixel of the preset views and photos")
    max_bounces: int = option(3, "surface interactions per path (1 = direct lighting only)")
    photos: int = option(8, "extra photos per object at random poses (photos/ capture)")
    relight_maps: int = option(2, "held-out lightings per object, 17 orbital views each (relight/<j>/ captures)")
    relight_spp: int = option(16, "samples per pixel of the held-out lighting views")
    layered: bool = option(False, "also render the preset views with the analytic layered material (out of basis)")
    workers: int = option(0, "processes (0: one per CPU); each renders whole objects with --threads torch threads")
    threads: int = option(1, "torch threads per process (more than 1 only when there are fewer objects than cores)")
    shard: str = option("0/1", "I/K: make only the objects whose index mod K is I (K shards may share one --out)")
    meshes: str = option("", "shared meshes folder (default: $NEUMATEX_SHARED/data/meshes or ../shared/data/meshes)")
    envmaps: str = option("", "shared environment maps folder (default: beside --meshes' default)")
    progress: bool = option(True, "show a progress bar")

    def meshes_dir(self) -> Path:
        return Path(self.meshes) if self.meshes else default_shared() / "meshes"

    def envmaps_dir(self) -> Path:
        return Path(self.envmaps) if self.envmaps else default_shared() / "envmaps"

    def shard_range(self) -> tuple[int, int]:
        """(I, K) of --shard, checked."""
        return parse_shard(self.shard)

    def check(self) -> None:
        """ValueError naming the first bad option."""
        if self.n < 0:
            raise ValueError(f"--n must be >= 0, got {self.n}")
        for name in ("resolution", "spp", "max_bounces", "relight_spp", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        for name in ("photos", "relight_maps", "workers"):
            if getattr(self, name) < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}")
        self.shard_range()

    def content(self) -> dict[str, Any]:
        """The options that decide the files' contents."""
        values = asdict(self)
        return {k: values[k] for k in CONTENT_FIELDS}

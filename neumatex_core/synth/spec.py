"""What one synthetic object is: shape, material, lighting, held-out lightings and render seeds, drawn from a seed.

`object_spec(split, index, seed, ...)` draws everything from numpy's SeedSequence([seed, split code, index]), so an
object depends only on (split, index, seed), the names of the shared meshes and maps and the number of held-out
lightings: not on the order objects are made in, on the process or on sharding.

Splits (docs/benchmark.md):

- train: a shared mesh with probability P_MESH_TRAIN, drawn from the shared meshes minus HELD_OUT_MESHES; else a
  procedural shape with probabilities PROCEDURAL_WEIGHTS.
- test: the benchmark. Objects cycle through five slots: slot 0 the held-out mesh teapot, slot 1 beetle, slots
  2-4 the procedural kinds in turn (40 objects: 8 teapot, 8 beetle, 5 each of sphere, torus, superquadric and
  blob, 4 unions). Its seed stream (split code 2) is disjoint from train's (1), so its procedural shapes, materials
  and lightings are draws training never sees.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.synth.lighting import LightingSpec, sample_lighting
from neumatex_core.synth.materials import MaterialSpec, sample_material_spec
from neumatex_core.synth.shapes import PROCEDURAL_KINDS, ShapeSpec

SPLITS = ("train", "test")
SPLIT_CODES = {"train": 1, "test": 2}
HELD_OUT_MESHES = ("teapot", "beetle")
P_MESH_TRAIN = 0.35
PROCEDURAL_WEIGHTS = {"sphere": 0.1, "torus": 0.15, "superquadric": 0.25, "blob": 0.25, "union": 0.25}
P_SKY = 0.3
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")
ENVMAP_SUFFIXES = (".exr", ".hdr")


@dataclass(frozen=True)
class ObjectSpec:
    """One object. id: "<split>-<index:06d>"; render_seed: view v of the preset views uses render_seed + v, the
    photos render_seed + 100 + k, held-out lighting j view v render_seed + 1000 (j + 1) + v; photo_seed: the
    random photo poses."""

    id: str
    split: str
    index: int
    seed: int
    shape: ShapeSpec
    material: MaterialSpec
    lighting: LightingSpec
    relight: tuple[LightingSpec, ...]
    render_seed: int
    photo_seed: int

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["material"] = self.material.to_json()
        return out


def object_id(split: str, index: int) -> str:
    return f"{split}-{index:06d}"


def shared_names(folder: Path | None, suffixes: tuple[str, ...]) -> list[str]:
    """Sorted file names in `folder` with one of `suffixes` ([] when the folder is None or missing)."""
    if folder is None or not Path(folder).is_dir():
        return []
    return sorted(p.name for p in Path(folder).iterdir() if p.suffix.lower() in suffixes and p.is_file())


def train_meshes(mesh_files: list[str]) -> list[str]:
    """Mesh names (file stems) the train split may use: every shared mesh except HELD_OUT_MESHES."""
    return [Path(m).stem for m in mesh_files if Path(m).stem not in HELD_OUT_MESHES]


def _shape(split: str, index: int, rng: np.random.Generator, mesh_files: list[str]) -> ShapeSpec:
    shape_seed = int(rng.integers(2**62))
    if split == "test":
        slot = index % 5
        stems = {Path(m).stem for m in mesh_files}
        if slot < 2 and HELD_OUT_MESHES[slot] in stems:
            return ShapeSpec("mesh", shape_seed, HELD_OUT_MESHES[slot])
        count = (index // 5) * 3 + max(slot - 2, 0)
        return ShapeSpec(PROCEDURAL_KINDS[count % len(PROCEDURAL_KINDS)], shape_seed)
    meshes = train_meshes(mesh_files)
    if meshes and rng.uniform() < P_MESH_TRAIN:
        return ShapeSpec("mesh", shape_seed, str(rng.choice(meshes)))
    kinds = list(PROCEDURAL_WEIGHTS)
    weights = np.asarray([PROCEDURAL_WEIGHTS[k] for k in kinds])
    return ShapeSpec(str(rng.choice(kinds, p=weights / weights.sum())), shape_seed)


def object_spec(split: str, index: int, seed: int, mesh_files: list[str], envmap_files: list[str],
                n_relight: int = 2) -> ObjectSpec:
    """The object `index` of `split` (see the module docstring). mesh_files / envmap_files: the shared file names
    (`shared_names`); held-out lighting j is a shared map other than the main one for even j, a sky for odd j."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), SPLIT_CODES[split], int(index)]))
    shape = _shape(split, index, rng, mesh_files)
    material = sample_material_spec(rng)
    lighting = sample_lighting(rng, envmap_files, P_SKY)
    relight = tuple(sample_lighting(rng, envmap_files, 0.0 if j % 2 == 0 else 1.0, avoid=lighting.map)
                    for j in range(n_relight))  # fmt: skip
    return ObjectSpec(object_id(split, index), split, index, int(seed), shape, material, lighting, relight,
                      render_seed=int(rng.integers(2**31)), photo_seed=int(rng.integers(2**31)))

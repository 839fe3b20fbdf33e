"""Synthetic data: procedural shapes, ground-truth neural materials, lighting, and the capture-format writer.

- `shapes.py`: procedural shapes and the shared meshes, normalised into the unit sphere;
- `materials.py`: regions, layered parameters from the family prior, base-colour patterns, `ProceduralMaterialField`
  (neural ground truth or the analytic layered material) and the PBR best match for G-buffers;
- `lighting.py`: shared maps under random rotation and exposure, procedural sun-and-sky maps;
- `spec.py`: what object `index` of a split is (`object_spec`), the held-out meshes of the test split;
- `writer.py`: one object -> one capture folder with ground truth; `rerender.py`: re-rendering it from G-buffers;
- `dataset.py`: `generate` (processes, resume, shards, manifest); `config.py`: `SynthConfig` (`neumatex synth`);
- `noise.py`: 3D Perlin noise; `profile.py`: where the time goes.
"""

from neumatex_core.synth.config import SynthConfig
from neumatex_core.synth.dataset import GenerateResult, generate
from neumatex_core.synth.spec import HELD_OUT_MESHES, ObjectSpec, object_spec

__all__ = ["HELD_OUT_MESHES", "GenerateResult", "ObjectSpec", "SynthConfig", "generate", "object_spec"]

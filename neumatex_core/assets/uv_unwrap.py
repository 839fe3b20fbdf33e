"""UV unwrapping with xatlas: charts, packing and per-vertex texture coordinates for baking.

xatlas cuts the surface into charts and packs them into [0, 1]^2; vertices on chart seams are duplicated (one copy
per chart), so the unwrapped mesh has more vertices than the input but the same triangles in the same order.
Positions and normals are copied through xatlas's vertex map, bit for bit.
"""

from __future__ import annotations

import numpy as np

from neumatex_core.geometry.mesh import Mesh

DEFAULT_PADDING = 4  # texels between charts at the packing resolution: room for bilinear lookups and dilation


def unwrap(mesh: Mesh, resolution: int = 512, padding: int = DEFAULT_PADDING) -> Mesh:
    """The mesh with xatlas uvs [V', 2] in [0, 1] (v up, see `fields.uv_textures`), packed for a square texture
    of `resolution` texels with `padding` texels between charts. Deterministic for a given mesh."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(mesh.vertices, dtype=np.float32),
                   np.ascontiguousarray(mesh.faces, dtype=np.uint32))  # fmt: skip
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    vmap, faces, uvs = atlas[0]
    vmap = vmap.astype(np.int64)
    normals = None if mesh.vertex_normals is None else mesh.vertex_normals[vmap]
    # xatlas's image rows grow downwards; flip v so that texel row 0 is the top (v = 1) of our textures.
    uv = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], axis=1).astype(np.float32)
    return Mesh(mesh.vertices[vmap].astype(np.float32), faces.astype(np.int64), normals, uv)

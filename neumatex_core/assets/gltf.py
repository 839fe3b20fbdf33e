"""glTF 2.0 (binary GLB) export of the PBR fallback: the mesh with its uvs and a metallic-roughness material.

One mesh, one primitive (POSITION, NORMAL, TEXCOORD_0, uint32 indices), one material with baseColorTexture
(sRGB PNG) and metallicRoughnessTexture (PNG: G roughness, B metallic, linear), double-sided (NeuMatEx shades both
sides). glTF texture coordinates have v down: TEXCOORD_0 = (u, 1 - v). The material's `extras` name the neural
asset (basis id) the fallback was fitted to.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.geometry.mesh import Mesh


def png_bytes(pixels: np.ndarray) -> bytes:
    """uint8 [H, W, C] -> PNG file bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels)).save(buf, format="PNG")
    return buf.getvalue()


def write_glb(path: Path, mesh: Mesh, base_color_png: bytes, metallic_roughness_png: bytes, name: str,
              extras: dict[str, Any] | None = None) -> None:
    """Write the GLB file (see the module docstring)."""
    import pygltflib as g

    if mesh.uvs is None or mesh.vertex_normals is None:
        raise ValueError("glTF export needs a mesh with uvs and vertex normals")
    pos = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    nrm = np.ascontiguousarray(mesh.vertex_normals, dtype=np.float32)
    tex = np.ascontiguousarray(np.stack([mesh.uvs[:, 0], 1 - mesh.uvs[:, 1]], axis=1), dtype=np.float32)
    idx = np.ascontiguousarray(mesh.faces, dtype=np.uint32).reshape(-1)
    blob = bytearray()
    views: list[g.BufferView] = []

    def add(data: bytes, target: int | None = None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    accessors = [
        g.Accessor(bufferView=add(pos.tobytes(), g.ARRAY_BUFFER), componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                   min=pos.min(0).tolist(), max=pos.max(0).tolist()),
        g.Accessor(bufferView=add(nrm.tobytes(), g.ARRAY_BUFFER), componentType=g.FLOAT, count=len(nrm), type=g.VEC3),
        g.Accessor(bufferView=add(tex.tobytes(), g.ARRAY_BUFFER), componentType=g.FLOAT, count=len(tex), type=g.VEC2),
        g.Accessor(bufferView=add(idx.tobytes(), g.ELEMENT_ARRAY_BUFFER), componentType=g.UNSIGNED_INT,
                   count=len(idx), type=g.SCALAR),
    ]  # fmt: skip
    images = [g.Image(bufferView=add(base_color_png), mimeType="image/png", name="base_color"),
              g.Image(bufferView=add(metallic_roughness_png), mimeType="image/png", name="metallic_roughness")]
    material = g.Material(
        name=f"{name}_pbr_fallback",
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorTexture=g.TextureInfo(index=0), metallicRoughnessTexture=g.TextureInfo(index=1),
            metallicFactor=1.0, roughnessFactor=1.0),
        doubleSided=True,
        extras={"neumatex": extras or {}},
    )  # fmt: skip
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="NeuMatEx"),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0, name=name)],
        meshes=[g.Mesh(name=name, primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2), indices=3, material=0)])],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
        images=images,
        samplers=[g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE,
                            wrapT=g.CLAMP_TO_EDGE)],
        textures=[g.Texture(source=0, sampler=0), g.Texture(source=1, sampler=0)],
        materials=[material],
    )  # fmt: skip
    gltf.set_binary_blob(bytes(blob))
    path.parent.mkdir(parents=True, exist_ok=True)
    gltf.save_binary(str(path))

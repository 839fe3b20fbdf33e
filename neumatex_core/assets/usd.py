"""USD export of the PBR fallback (usd-core): a Y-up stage with the mesh and a UsdPreviewSurface material.

/<name> (Xform, default prim) holds Mesh (points, triangle faces, vertex normals, primvars:st with v up, double
sided) bound to Materials/PBRFallback: a UsdPreviewSurface (metallic workflow) whose diffuseColor reads the sRGB
base colour PNG and whose roughness / metallic read the G / B channels of the glTF-style metallic-roughness PNG
(raw colour space), through UsdUVTexture nodes driven by a UsdPrimvarReader_float2 of "st". Texture paths are
relative to the USD file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from neumatex_core.geometry.mesh import Mesh


def usd_name(name: str) -> str:
    """A valid USD prim name from any string."""
    clean = re.sub(r"[^A-Za-z0-9_]", "_", name) or "asset"
    return clean if not clean[0].isdigit() else "_" + clean


def write_usd(path: Path, mesh: Mesh, base_color_file: str, metallic_roughness_file: str, name: str) -> None:
    """Write a .usda (or .usdc/.usd) stage; texture files are paths relative to `path`'s folder."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    if mesh.uvs is None or mesh.vertex_normals is None:
        raise ValueError("USD export needs a mesh with uvs and vertex normals")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root_path = "/" + usd_name(name)
    root = UsdGeom.Xform.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())
    geom = UsdGeom.Mesh.Define(stage, root_path + "/Mesh")
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.vertices, dtype=np.float32)))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(mesh.num_faces, 3, dtype=np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.reshape(-1),
                                                                                  dtype=np.int32)))
    geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.vertex_normals, dtype=np.float32)))
    geom.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateDoubleSidedAttr(True)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    st = UsdGeom.PrimvarsAPI(geom).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(mesh.uvs, dtype=np.float32)))

    mat_path = root_path + "/Materials/PBRFallback"
    material = UsdShade.Material.Define(stage, mat_path)
    surface = UsdShade.Shader.Define(stage, mat_path + "/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    reader = UsdShade.Shader.Define(stage, mat_path + "/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    st_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    def texture(node: str, file: str, colour_space: str) -> UsdShade.Shader:
        tex = UsdShade.Shader.Define(stage, f"{mat_path}/{node}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_out)
        return tex

    base = texture("BaseColorTexture", base_color_file, "sRGB")
    mr = texture("MetallicRoughnessTexture", metallic_roughness_file, "raw")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        base.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(
        mr.CreateOutput("g", Sdf.ValueTypeNames.Float))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).ConnectToSource(
        mr.CreateOutput("b", Sdf.ValueTypeNames.Float))
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()

"""Materials: the Material interface, the PBR material (and, later, the layered and neural materials)."""

from neumatex_core.materials.base import Material
from neumatex_core.materials.pbr import PBRMaterial

__all__ = ["Material", "PBRMaterial"]

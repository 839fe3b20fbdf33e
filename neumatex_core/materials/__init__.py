"""Materials: the Material interface, the PBR material, the analytic layered material and the neural basis."""

from neumatex_core.materials.base import Material
from neumatex_core.materials.layered import LayeredMaterial
from neumatex_core.materials.pbr import PBRMaterial

__all__ = ["LayeredMaterial", "Material", "PBRMaterial"]

"""HDR environment lighting."""

from neumatex_core.lighting.envmap import EnvironmentMap, EnvmapError

__all__ = ["EnvironmentMap", "EnvmapError"]

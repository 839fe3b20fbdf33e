"""The torch Monte Carlo path tracer shared by data synthesis, TTO and evaluation."""

from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene

__all__ = ["PathTracer", "PathTracerConfig", "Scene"]

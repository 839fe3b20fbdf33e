"""NeuMatEx core library: capture format, geometry, lighting, materials and the torch path tracer.

This package imports no web, queue or database code; services and workers are thin layers over
`neumatex_core.pipeline` (see docs/architecture.md section 1).
"""

__version__ = "0.1.0"

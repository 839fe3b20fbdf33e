"""NeuMatEx job service: the FastAPI app (routes, schemas, models, crud, storage, auth) over a SQL job database.

The workers (package `workers`) run the pipeline stages; both share `services.core` (settings, database) and
`services.models`. Run everything on one machine with `python -m services serve` (docs/service.md).
"""

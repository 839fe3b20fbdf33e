"""Celery workers: one task per pipeline stage (neumatex_core.pipeline.run_stage), chained by each task sending the
next; the job row in the database is the source of truth (services.models.Job)."""

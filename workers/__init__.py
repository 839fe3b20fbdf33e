"""Celery workers: a thin wrapper running one pipeline stage per task (neumatex_core.pipeline.run_stage) and the
reaper's task from beat; every change of a job's state goes through services.lifecycle (workers -> services only)."""

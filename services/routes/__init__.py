"""API routes under /v1 (captures, uploads, jobs, assets) and the unversioned health, metrics and dashboard."""

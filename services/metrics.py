"""Prometheus metrics. Read from the database and the broker at scrape time (so every API replica reports the
same numbers): jobs by state, stage durations (a histogram over finished stage runs), stage runs by status,
queue depth per queue; plus this process's HTTP request counts and latencies."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from neumatex_core.pipeline import STAGES
from services.core.config import get_settings
from services.core.db import session_scope
from services.models import JOB_STATES, Job, StageRun

BUCKETS = (0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1800, 3600, 4 * 3600)
REGISTRY = CollectorRegistry()
REQUESTS = Counter("neumatex_http_requests_total", "HTTP requests", ["method", "route", "status"], registry=REGISTRY)
LATENCY = Histogram("neumatex_http_request_seconds", "HTTP request latency", ["route"], registry=REGISTRY,
                    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10))  # fmt: skip


class ServiceCollector(Collector):
    def collect(self) -> Iterator[GaugeMetricFamily | HistogramMetricFamily]:
        jobs = GaugeMetricFamily("neumatex_jobs", "Jobs by state", labels=["state"])
        runs = GaugeMetricFamily("neumatex_stage_runs", "Stage runs by stage and status", labels=["stage", "status"])
        hist = HistogramMetricFamily("neumatex_stage_duration_seconds", "Duration of finished stages",
                                     labels=["stage"])  # fmt: skip
        with session_scope() as s:
            counts = dict(s.execute(select(Job.state, func.count()).group_by(Job.state)).all())
            for state in JOB_STATES:
                jobs.add_metric([state], float(counts.get(state, 0)))
            for stage, status, n in s.execute(select(StageRun.stage, StageRun.status, func.count())
                                              .group_by(StageRun.stage, StageRun.status)).all():  # fmt: skip
                runs.add_metric([stage, status], float(n))
            for stage in STAGES:
                secs = [float(x or 0.0) for x in s.scalars(select(StageRun.seconds).where(
                    StageRun.stage == stage, StageRun.status == "finished", StageRun.seconds.is_not(None)))]
                buckets = [(str(b), float(sum(1 for x in secs if x <= b))) for b in BUCKETS]
                buckets.append(("+Inf", float(len(secs))))
                hist.add_metric([stage], buckets, sum(secs))
        yield jobs
        yield runs
        yield hist
        depth = GaugeMetricFamily("neumatex_queue_depth", "Messages waiting in the broker queue", labels=["queue"])
        try:
            import redis

            client = redis.Redis.from_url(get_settings().redis_url, socket_timeout=1, socket_connect_timeout=1)
            from services.queue import QUEUES

            for q in QUEUES:
                depth.add_metric([q], float(client.llen(q)))
            client.close()
        except Exception:  # broker down: the gauge is absent; /readyz says why
            return
        yield depth


REGISTRY.register(ServiceCollector())

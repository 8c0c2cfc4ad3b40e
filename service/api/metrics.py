"""``GET /metrics``: Prometheus text exposition (format 0.0.4), computed from the job table, so the
numbers survive restarts and agree between API replicas."""

from __future__ import annotations

from service.store import Store

SOLVE_BUCKETS = [0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1800, 3600]
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def render(store: Store, backend_name: str, health: dict) -> str:
    lines = [
        "# HELP acinoset_jobs Jobs in the job table by status.",
        "# TYPE acinoset_jobs gauge",
    ]
    for status, n in store.status_counts().items():
        lines.append(f'acinoset_jobs{{status="{status}"}} {n}')
    counts, total, seconds = store.solve_seconds_histogram(SOLVE_BUCKETS)
    lines += [
        "# HELP acinoset_solve_seconds Wall time of succeeded jobs' runs, from start to stored result.",
        "# TYPE acinoset_solve_seconds histogram",
    ]
    for b, c in zip(SOLVE_BUCKETS, counts):
        lines.append(f'acinoset_solve_seconds_bucket{{le="{b:g}"}} {c}')
    lines += [
        f'acinoset_solve_seconds_bucket{{le="+Inf"}} {total}',
        f"acinoset_solve_seconds_sum {seconds:.6f}",
        f"acinoset_solve_seconds_count {total}",
        "# HELP acinoset_workers Solves that can run at once (embedded) or connected workers (rq).",
        "# TYPE acinoset_workers gauge",
        f'acinoset_workers{{backend="{backend_name}"}} {int(health.get("workers", 0))}',
        "# HELP acinoset_up 1 if the backend can run jobs.",
        "# TYPE acinoset_up gauge",
        f'acinoset_up{{backend="{backend_name}"}} {1 if health.get("ok") else 0}',
    ]
    return "\n".join(lines) + "\n"

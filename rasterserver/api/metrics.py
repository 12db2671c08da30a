"""Request counters and latency histograms in the Prometheus text format (per process)."""

from __future__ import annotations

import threading
from collections import defaultdict

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class Metrics:
    """Counts requests by method, route template and status, and their durations."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count: dict[tuple[str, str, int], int] = defaultdict(int)
        self._buckets: dict[tuple[str, str], list[int]] = {}
        self._sum: dict[tuple[str, str], float] = defaultdict(float)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        """Record one finished request (``route`` is the template, never the path)."""
        with self._lock:
            self._count[(method, route, status)] += 1
            counts = self._buckets.setdefault((method, route), [0] * (len(BUCKETS) + 1))
            for i, bound in enumerate(BUCKETS):
                if seconds <= bound:
                    counts[i] += 1
            counts[-1] += 1
            self._sum[(method, route)] += seconds

    def render(self, extra: dict[str, float] | None = None) -> str:
        """Return every metric in the Prometheus exposition format."""
        lines = ["# TYPE rasterserver_requests_total counter"]
        with self._lock:
            for (method, route, status), n in sorted(self._count.items()):
                lines.append(f'rasterserver_requests_total{{method="{method}",route="{route}",'
                             f'status="{status}"}} {n}')
            lines.append("# TYPE rasterserver_request_seconds histogram")
            for (method, route), counts in sorted(self._buckets.items()):
                labels = f'method="{method}",route="{route}"'
                for bound, n in zip(BUCKETS, counts, strict=False):
                    lines.append(
                        f'rasterserver_request_seconds_bucket{{{labels},le="{bound}"}} {n}')
                lines.append(f'rasterserver_request_seconds_bucket{{{labels},le="+Inf"}} '
                             f"{counts[-1]}")
                lines.append(f"rasterserver_request_seconds_sum{{{labels}}} "
                             f"{self._sum[(method, route)]:.6f}")
                lines.append(f"rasterserver_request_seconds_count{{{labels}}} {counts[-1]}")
        for name, value in (extra or {}).items():
            lines += [f"# TYPE {name} gauge", f"{name} {value:g}"]
        return "\n".join(lines) + "\n"

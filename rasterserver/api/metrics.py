"""Request counts and latency histograms in the Prometheus text format (``prometheus_client``).

Two modes, chosen when :class:`Metrics` is built:

single process (``PROMETHEUS_MULTIPROC_DIR`` unset)
    Each :class:`Metrics` has its own :class:`~prometheus_client.CollectorRegistry`, never the
    global default one, so several apps in one process (the tests) count apart.
multiprocess (``PROMETHEUS_MULTIPROC_DIR`` set, as ``rasterserver serve --workers N`` does)
    Every worker writes its counts to its own files in that directory and a scrape, whichever
    worker answers it, sums the files of all workers with
    :class:`~prometheus_client.multiprocess.MultiProcessCollector`. Counters and histograms
    of a worker that exited stay in the sum, so totals never go backwards when uvicorn
    replaces a worker. There is one :class:`Metrics` per worker process in this mode: two in
    one process would write the same series of the same file.

Labels are the route template (``/patients/{patient}``), never the concrete path: paths can
carry patient identifiers, which must not reach the metrics.
"""

from __future__ import annotations

import atexit
import os
from collections.abc import Iterator, Mapping

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest, values
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector, mark_process_dead

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"


class _Gauges:
    """A collector of fixed gauge values, made afresh for each scrape."""

    def __init__(self, gauges: Mapping[str, float]) -> None:
        self._gauges = gauges

    def collect(self) -> Iterator[GaugeMetricFamily]:
        for name, value in self._gauges.items():
            yield GaugeMetricFamily(name, "Read when scraped (alike in every worker).",
                                    value=value)


class Metrics:
    """Counts requests by method, route template and status, and their durations.

    Parameters
    ----------
    multiproc_dir : str, optional
        Directory shared by all worker processes; by default ``$PROMETHEUS_MULTIPROC_DIR``.
        Without one, counts stay in this object's own registry.

    Raises
    ------
    RuntimeError
        In multiprocess mode when the directory does not exist, or when ``prometheus_client``
        was imported before the variable was set: it then keeps values in memory and the
        workers' counts would never be summed.
    """

    def __init__(self, multiproc_dir: str | None = None) -> None:
        self.multiproc_dir = multiproc_dir or os.environ.get(MULTIPROC_ENV) or None
        if self.multiproc_dir:
            # fail at start rather than at the first scrape
            if not os.path.isdir(self.multiproc_dir):
                raise RuntimeError(f"{MULTIPROC_ENV}={self.multiproc_dir} is not a directory")
            # prometheus_client picks its value store once, at import, from the environment
            if not getattr(values.ValueClass, "_multiprocess", False):
                raise RuntimeError(f"{MULTIPROC_ENV} must be set before prometheus_client is "
                                   "imported, or the workers' metrics are not shared")
            # in multiprocess mode the values live in files; registering the metrics in the
            # scrape registry as well would export every series twice
            self.registry = None
            # uvicorn has no hook in the parent when a worker exits, so the worker marks
            # itself on a clean exit (spawned workers run atexit handlers). Only 'live*'
            # gauges depend on it (none today); counters and histograms are summed anyway.
            atexit.register(mark_process_dead, os.getpid(), self.multiproc_dir)
        else:
            self.registry = CollectorRegistry(auto_describe=True)
        self._requests = Counter(
            "rasterserver_requests", "Finished HTTP requests.",
            ["method", "route", "status"], registry=self.registry)
        self._seconds = Histogram(
            "rasterserver_request_seconds", "Time to the start of the response, in seconds.",
            ["method", "route"], buckets=BUCKETS, registry=self.registry)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        """Record one finished request.

        Parameters
        ----------
        method : str
            HTTP method.
        route : str
            The route template (``/patients/{patient}``), never the concrete path.
        status : int
            Status code of the response.
        seconds : float
            Time from the request to the start of the response.
        """
        self._requests.labels(method, route, str(status)).inc()
        self._seconds.labels(method, route).observe(seconds)

    def render(self, extra: Mapping[str, float] | None = None) -> str:
        """Return every metric in the Prometheus text format (version 0.0.4).

        Parameters
        ----------
        extra : dict of str to float, optional
            Gauges computed at scrape time, by name (the jobs in the catalogue). They are the
            same whichever worker answers, so they are not stored in the shared files.

        Returns
        -------
        str
            Request counts and latencies: of all workers in multiprocess mode, else of this
            object.
        """
        if self.multiproc_dir:
            # a registry per scrape, as prometheus_client documents for multiprocess mode
            source = CollectorRegistry()
            MultiProcessCollector(source, path=self.multiproc_dir)
        else:
            assert self.registry is not None  # made when not in multiprocess mode
            source = self.registry
        text_out = generate_latest(source)
        if extra:
            gauges = CollectorRegistry(auto_describe=True)
            gauges.register(_Gauges(extra))
            text_out += generate_latest(gauges)
        return text_out.decode()

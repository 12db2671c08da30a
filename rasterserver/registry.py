"""Discovery of stage plugins through the ``rasterserver.stages`` entry-point group.

The built-in stages are found exactly like a third-party package's: each distribution lists
its stages as entry points, ``<plugin name> = <module>:<Stage subclass or instance>``. Entry
points are read once per :class:`Registry` and each plugin is imported only when first needed.
A plugin that fails to import, or that is not a valid :class:`~rasterserver.stage.Stage`, is
listed as broken with the reason and never affects the others.
"""

from __future__ import annotations

import importlib
import logging
import re
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Literal

from rasterserver.errors import InputError, NotFoundError
from rasterserver.records import Record, record_types
from rasterserver.stage import BUILTIN_STAGE_KINDS, Stage, stage_problems

__all__ = [
    "BUILTIN_DISTRIBUTION",
    "STAGE_GROUP",
    "GraphEdge",
    "PluginInfo",
    "Registry",
    "get_registry",
]

STAGE_GROUP = "rasterserver.stages"
"""The entry-point group stage plugins register in."""

BUILTIN_DISTRIBUTION = "rasterserver"

#: The modules of rasterserver that define the built-in record kinds. A miss in
#: :meth:`Registry.record_type` imports these (NumPy only) before it loads every plugin
#: (SciPy, open3d, ...): ``verify`` reads stored results of built-in kinds and should not pay
#: for the plugins.
CORE_RECORD_MODULES = (
    "rasterserver.records_lines",
    "rasterserver.records_surface",
    "rasterserver.records_analysis",
    "rasterserver.records_comparison",
)
"""Distribution of the built-in stages; preferred by :meth:`Registry.default_for` on a tie."""

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PluginInfo:
    """What the registry knows about one entry point, whether it loaded or not.

    Attributes
    ----------
    name : str
        Plugin name (the entry point's name, which must equal the stage's ``name``).
    entry_point : str
        The entry point's value, ``module:attribute``.
    status : {"ok", "broken"}
        Whether the plugin can be used.
    stage : str or None
        Stage kind implemented; None when the plugin could not be loaded.
    version : str or None
        Algorithm version; None when the plugin could not be loaded.
    input_kind, output_kind : str or None
        ``kind`` of the input and output record types.
    package, package_version : str or None
        Name and version of the distribution that provides the entry point.
    summary : str or None
        First line of the stage's docstring.
    error : str or None
        Why the plugin is broken; None when it is ok.
    """

    name: str
    entry_point: str
    status: Literal["ok", "broken"]
    stage: str | None = None
    version: str | None = None
    input_kind: str | None = None
    output_kind: str | None = None
    package: str | None = None
    package_version: str | None = None
    summary: str | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        """True when the plugin loaded and is a valid stage."""
        return self.status == "ok"

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a JSON-ready dict."""
        return asdict(self)


@dataclass(frozen=True)
class GraphEdge:
    """One working plugin as an edge of the stage graph.

    Attributes
    ----------
    input_kind, output_kind : str
        Record kinds taken and given.
    stage : str
        Stage kind.
    plugin, version : str
        Plugin name and algorithm version.
    default : bool
        Whether it is the plugin used for its kind when none is named.
    """

    input_kind: str
    stage: str
    output_kind: str
    plugin: str
    version: str
    default: bool


@dataclass(frozen=True)
class _Loaded:
    info: PluginInfo
    stage: Stage[Any, Any] | None


def _distribution(ep: EntryPoint) -> tuple[str | None, str | None]:
    dist = ep.dist
    if dist is None:
        return None, None
    return dist.name, dist.version


def _normalize(distribution: str | None) -> str | None:
    # PEP 503 normalisation: "Raster_Server" and "raster-server" are one distribution.
    return None if distribution is None else re.sub(r"[-_.]+", "-", distribution).lower()


def _listing_key(info: PluginInfo) -> tuple[int, str, str]:
    # The built-in chain in processing order, then other kinds, then the unloadable ones.
    if info.stage in BUILTIN_STAGE_KINDS:
        return (BUILTIN_STAGE_KINDS.index(info.stage), "", info.name)
    if info.stage is not None:
        return (len(BUILTIN_STAGE_KINDS), info.stage, info.name)
    return (len(BUILTIN_STAGE_KINDS) + 1, "", info.name)


class Registry:
    """The stage plugins installed in this environment.

    Parameters
    ----------
    group : str, optional
        Entry-point group to read; :data:`STAGE_GROUP` unless testing.
    defaults : Mapping of str to str, optional
        Plugin name to use per stage kind, overriding the rule of :meth:`default_for`
        (this is where configuration plugs in).
    builtin_distribution : str, optional
        Distribution whose plugins :meth:`default_for` prefers; :data:`BUILTIN_DISTRIBUTION`.
    warn_broken : bool, optional
        Log a warning for each broken plugin when it is loaded (default); off for callers
        that report broken plugins themselves, like ``rasterserver plugins``.

    Notes
    -----
    Thread-safe: the HTTP server may resolve plugins from several threads.
    """

    def __init__(
        self,
        group: str = STAGE_GROUP,
        *,
        defaults: Mapping[str, str] | None = None,
        builtin_distribution: str = BUILTIN_DISTRIBUTION,
        warn_broken: bool = True,
    ) -> None:
        self.group = group
        self.warn_broken = warn_broken
        self.builtin_distribution = builtin_distribution
        self.defaults: dict[str, str] = dict(defaults or {})
        self._lock = threading.RLock()
        self._entry_points: dict[str, list[EntryPoint]] | None = None
        self._loaded: dict[str, list[_Loaded]] = {}
        # Every plugin described, sorted: resolving a chain asks for it a few hundred times,
        # and loading is settled once every name has been loaded (until discover()).
        self._all_infos: list[PluginInfo] | None = None
        # The same settled state decides the stage kinds and each kind's unconfigured default;
        # a chain resolution asks for them about fifty times (0.5 ms of a 20 ms chain).
        self._kinds: list[str] | None = None
        self._found_defaults: dict[str, Stage[Any, Any]] = {}

    def discover(self) -> Registry:
        """Read the entry points again and forget every loaded plugin.

        Returns
        -------
        Registry
            This registry, for chaining.
        """
        with self._lock:
            found: dict[str, list[EntryPoint]] = {}
            for ep in entry_points(group=self.group):
                found.setdefault(ep.name, []).append(ep)
            self._entry_points = found
            self._loaded = {}
            self._all_infos = None
            self._kinds = None
            self._found_defaults = {}
        return self

    def _eps(self) -> dict[str, list[EntryPoint]]:
        with self._lock:
            if self._entry_points is None:
                self.discover()
            assert self._entry_points is not None
            return self._entry_points

    def names(self) -> list[str]:
        """Return the names of all registered plugins, broken ones included, without loading."""
        return sorted(self._eps())

    def _load_name(self, name: str) -> list[_Loaded]:
        with self._lock:
            if name not in self._loaded:
                eps = self._eps()[name]
                if len(eps) == 1:
                    self._loaded[name] = [self._load(eps[0])]
                else:
                    # Two packages claiming one name: choosing either would make results depend
                    # on install order, so neither is used until one is removed.
                    claims = ", ".join(
                        f"{pkg or '?'} {ver or '?'} ({ep.value})"
                        for ep in eps
                        for pkg, ver in [_distribution(ep)]
                    )
                    self._loaded[name] = [
                        self._broken(ep, f"plugin name registered more than once: {claims}")
                        for ep in eps
                    ]
            return self._loaded[name]

    def _broken(self, ep: EntryPoint, reason: str) -> _Loaded:
        package, package_version = _distribution(ep)
        if self.warn_broken:
            logger.warning("stage plugin %s (%s) is broken: %s", ep.name, ep.value, reason)
        info = PluginInfo(
            name=ep.name,
            entry_point=ep.value,
            status="broken",
            package=package,
            package_version=package_version,
            error=reason,
        )
        return _Loaded(info, None)

    def _load(self, ep: EntryPoint) -> _Loaded:
        try:
            obj = ep.load()
        # Anything a plugin's import raises, SyntaxError included, must only break that plugin.
        except Exception as exc:
            return self._broken(ep, f"import failed: {type(exc).__name__}: {exc}")
        if not (isinstance(obj, Stage) or (isinstance(obj, type) and issubclass(obj, Stage))):
            what = obj.__name__ if isinstance(obj, type) else type(obj).__name__
            return self._broken(
                ep, f"{ep.value} is {what!r}, not a rasterserver.stage.Stage subclass or instance"
            )
        problems = stage_problems(obj)
        if problems:
            return self._broken(ep, "; ".join(problems))
        if isinstance(obj, type):
            try:
                stage = obj()
            except Exception as exc:
                return self._broken(
                    ep, f"{ep.value}() could not be instantiated: {type(exc).__name__}: {exc}"
                )
        else:
            stage = obj
        if stage.name != ep.name:
            return self._broken(
                ep, f"entry point name {ep.name!r} differs from the stage's name {stage.name!r}"
            )
        package, package_version = _distribution(ep)
        doc = (type(stage).__doc__ or "").strip()
        info = PluginInfo(
            name=stage.name,
            entry_point=ep.value,
            status="ok",
            stage=stage.stage,
            version=stage.version,
            input_kind=stage.input_type.kind,
            output_kind=stage.output_type.kind,
            package=package,
            package_version=package_version,
            summary=doc.splitlines()[0] if doc else None,
        )
        return _Loaded(info, stage)

    def infos(self, stage: str | None = None) -> list[PluginInfo]:
        """Load every plugin and describe it; broken ones are included.

        Parameters
        ----------
        stage : str, optional
            Only plugins of this stage kind (broken plugins whose kind is unknown are left out).

        Returns
        -------
        list of PluginInfo
            In processing order of the built-in chain, then by kind and name; broken plugins
            of unknown kind last.
        """
        with self._lock:
            if self._all_infos is None:
                self._all_infos = sorted(
                    (loaded.info for name in self.names() for loaded in self._load_name(name)),
                    key=_listing_key,
                )
            infos = list(self._all_infos)
        if stage is not None:
            infos = [info for info in infos if info.stage == stage]
        return infos

    def info(self, name: str) -> PluginInfo:
        """Describe the plugin called ``name``, loading only it.

        Raises
        ------
        NotFoundError
            When no entry point has that name; the message lists the available plugins.
        """
        if name not in self._eps():
            raise NotFoundError(self._unknown_message(name))
        return self._load_name(name)[0].info

    def _unknown_message(self, name: str) -> str:
        usable = [info.name for info in self.infos() if info.ok]
        if usable:
            available = f"available: {', '.join(sorted(usable))}"
        else:
            available = f"no working stage plugins are installed (entry-point group {self.group})"
        broken = sorted({info.name for info in self.infos() if not info.ok})
        if broken:
            available += f"; broken: {', '.join(broken)}"
        return f"no stage plugin named {name!r}; {available}"

    def get(self, name: str) -> Stage[Any, Any]:
        """Return the stage called ``name``, importing its module on first use.

        Parameters
        ----------
        name : str
            Plugin name, e.g. ``"peaks.first-moment"``.

        Returns
        -------
        Stage
            The plugin, ready for :func:`~rasterserver.stage.run_stage`.

        Raises
        ------
        NotFoundError
            When no plugin has that name (the message lists the available ones) or the
            plugin is broken (the message says ``broken: <reason>``).
        """
        if name not in self._eps():
            raise NotFoundError(self._unknown_message(name))
        loaded = self._load_name(name)[0]
        if loaded.stage is None:
            info = loaded.info
            package = f"{info.package or '?'} {info.package_version or '?'}"
            raise NotFoundError(f"stage plugin {name!r} from {package} is broken: {info.error}")
        return loaded.stage

    def for_stage(self, kind: str) -> list[Stage[Any, Any]]:
        """Return the working plugins that implement stage ``kind``, by name.

        Parameters
        ----------
        kind : str
            Stage kind, e.g. ``"peaks"``.

        Returns
        -------
        list of Stage
            Possibly empty.
        """
        return [
            self.get(info.name)
            for info in sorted(self.infos(kind), key=lambda i: i.name)
            if info.ok
        ]

    def stage_kinds(self) -> list[str]:
        """Return the stage kinds that at least one working plugin implements, in chain order."""
        with self._lock:
            if self._kinds is None:
                kinds = {info.stage for info in self.infos() if info.ok and info.stage is not None}
                self._kinds = sorted(
                    kinds,
                    key=lambda k: (
                        BUILTIN_STAGE_KINDS.index(k)
                        if k in BUILTIN_STAGE_KINDS
                        else len(BUILTIN_STAGE_KINDS),
                        k,
                    ),
                )
            return list(self._kinds)

    def default_for(self, kind: str) -> Stage[Any, Any]:
        """Return the plugin used for stage ``kind`` when the user names none.

        The choice is deterministic: the plugin configured in ``defaults`` if any; otherwise,
        among the working plugins of that kind, those of the built-in distribution are
        preferred (installing a package must not silently change the clinical default), and
        of those the first by name.

        Parameters
        ----------
        kind : str
            Stage kind, e.g. ``"peaks"``.

        Returns
        -------
        Stage
            The default plugin.

        Raises
        ------
        NotFoundError
            When no working plugin implements ``kind``, or the configured one does not exist
            or is broken.
        InputError
            When the configured default implements another stage kind.
        """
        configured = self.defaults.get(kind)
        if configured is not None:
            stage = self.get(configured)
            if stage.stage != kind:
                raise InputError(
                    f"the default for stage {kind!r} is configured as {configured!r}, "
                    f"which implements stage {stage.stage!r}"
                )
            return stage
        with self._lock:
            found = self._found_defaults.get(kind)
        if found is not None:
            return found
        candidates = [info for info in self.infos(kind) if info.ok]
        if not candidates:
            kinds = ", ".join(self.stage_kinds()) or "none"
            raise NotFoundError(
                f"no working stage plugin implements stage {kind!r} (implemented: {kinds})"
            )
        builtin = [
            info
            for info in candidates
            if _normalize(info.package) == _normalize(self.builtin_distribution)
        ]
        chosen = min(builtin or candidates, key=lambda info: info.name)
        stage = self.get(chosen.name)
        with self._lock:
            self._found_defaults[kind] = stage
        return stage

    def graph(self) -> list[GraphEdge]:
        """The stage graph: one edge per working plugin, from the record kind it takes to the
        one it gives, in chain order (built-in kinds first).

        Returns
        -------
        list of GraphEdge
        """
        edges = [
            GraphEdge(
                info.input_kind or "?",
                info.stage or "?",
                info.output_kind or "?",
                info.name,
                info.version or "?",
                info.name == self.default_for(info.stage or "").name,
            )
            for info in self.infos()
            if info.ok
        ]
        return edges

    def record_type(self, kind: str) -> type[Record]:
        """Return the record class of ``kind``, as the installed plugins declare it.

        A record class is known once its module is imported, which a fresh process may not
        have done when it reads a stored result (``verify`` reads files no stage has run for).
        The plugins decide, not import order: on a miss rasterserver's own record modules
        (:data:`CORE_RECORD_MODULES`, the built-in kinds) are imported, and if the kind is
        still unknown every plugin is loaded, which imports the record classes its stages take
        and give.

        Parameters
        ----------
        kind : str
            Record kind, e.g. ``"peaks"``.

        Returns
        -------
        type of Record

        Raises
        ------
        NotFoundError
            When no installed plugin takes or gives records of that kind.
        """
        known = record_types()
        if kind in known:
            return known[kind]
        for module in CORE_RECORD_MODULES:
            importlib.import_module(module)
        known = record_types()
        if kind in known:
            return known[kind]
        for info in self.infos():
            if info.ok:
                stage = self.get(info.name)
                for cls in (stage.input_type, stage.output_type):
                    if cls.kind == kind:
                        return cls
        known = record_types()
        if kind in known:
            return known[kind]
        raise NotFoundError(
            f"no installed stage plugin takes or gives {kind!r} records "
            f"(known: {', '.join(sorted(known)) or 'none'})"
        )


_shared: Registry | None = None
_shared_lock = threading.Lock()


def get_registry() -> Registry:
    """Return the registry shared by this process; discovery happens on first use.

    Call ``get_registry().discover()`` to pick up plugins installed since (tests do).
    """
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = Registry()
        return _shared

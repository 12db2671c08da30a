"""A chain named on the command line, and the stored results that chain made.

``rasterserver diff``, ``reprocess`` and ``prune`` name chains in one string, the way
``process --stage`` names plugins, with versions and parameters added::

    default                                   the installed plugins with default parameters
    peaks=peaks.first-moment                  another plugin for a stage (like --stage)
    peaks=peaks.first-moment@2                results of algorithm version 2 (also an old one)
    peaks.bias_fraction=0.2                   a parameter of a stage (JSON value, else text)
    peaks=peaks.first-moment@2,peaks.min_height=4,numbers=numbers.code-window

Items are separated by commas; ``KIND=PLUGIN[@VERSION]`` picks a plugin, ``KIND.NAME=VALUE``
sets a parameter. A stage not named uses the installed default plugin, version and parameters
(resolved like ``process``). A pinned version other than the installed one cannot have its
parameters validated here, so its results match whatever their parameters (unless parameters
are given for that stage: then they must hash the same as the installed plugin's).

Which stored results a chain made
---------------------------------
Results are matched on their provenance, not recomputed: a result of the chain's first stage
has no parent and the first step's plugin, version and parameters hash; each next one is a
child of the previous with the next step's. Several matches (another calibration, a second
frame) resolve to the newest. This needs no calibration or frame: it finds what was stored,
also for plugin versions no longer installed.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from rasterserver.errors import InputError
from rasterserver.registry import Registry, get_registry

__all__ = [
    "ChainSpec",
    "ResultRow",
    "StepPattern",
    "describe_patterns",
    "match_path",
    "parse_chain",
    "result_rows",
]


@dataclass(frozen=True)
class StepPattern:
    """What a stored result of one step must carry: None matches anything."""

    kind: str
    plugin: str
    version: str | None
    params_hash: str | None

    def matches(self, row: ResultRow) -> bool:
        """Whether ``row`` was made by this step."""
        return (
            row.stage == self.kind
            and row.plugin == self.plugin
            and (self.version is None or row.plugin_version == self.version)
            and (self.params_hash is None or row.params_hash == self.params_hash)
        )

    def describe(self) -> str:
        """``plugin@version`` (``@*`` when any version matches)."""
        return f"{self.plugin}@{self.version or '*'}"


@dataclass(frozen=True)
class ResultRow:
    """The provenance of a stored result that matching needs (light: no file read)."""

    id: int
    acquisition_id: int
    parent_id: int | None
    stage: str
    plugin: str
    plugin_version: str
    params_hash: str
    output_checksum: str
    store_path: str
    record_kind: str


@dataclass(frozen=True)
class ChainSpec:
    """A chain as named: plugins, pinned versions and parameters per stage kind.

    Attributes
    ----------
    text : str
        As given (``"default"`` when empty).
    stages : dict of str to str
        Plugin per stage kind, as ``process --stage``.
    versions : dict of str to str
        Pinned algorithm version per stage kind.
    params : dict of str to dict
        Parameters per stage kind.
    """

    text: str = "default"
    stages: dict[str, str] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    params: dict[str, dict[str, Any]] = field(default_factory=dict)

    def patterns(self, until: str, *, registry: Registry | None = None) -> list[StepPattern]:
        """The steps up to stage kind ``until``, as patterns of stored results.

        Raises
        ------
        InputError, NotFoundError
            As :func:`rasterserver.pipeline.resolve_chain`: unknown kinds or plugins, bad
            parameters; or a version pinned for a stage not on the way to ``until``.
        """
        from rasterserver.pipeline import resolve_chain

        registry = registry or get_registry()
        steps = resolve_chain(self.stages, params=self.params, until=until, registry=registry)
        kinds = {step.kind for step in steps}
        stray = sorted(set(self.versions) - kinds - set(self.stages))
        if stray:
            raise InputError(f"chain {self.text!r}: version pinned for stage(s) "
                             f"{', '.join(stray)}, not on the way to {until!r}")
        out = []
        for step in steps:
            pinned = self.versions.get(step.kind)
            if pinned is None or pinned == step.version:
                out.append(StepPattern(step.kind, step.plugin, step.version, step.params_hash))
            else:
                # another version's parameters cannot be validated by the installed plugin
                digest = step.params_hash if step.kind in self.params else None
                out.append(StepPattern(step.kind, step.plugin, pinned, digest))
        return out

    def to_process(self) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
        """``(chain, params)`` for :func:`rasterserver.processing_jobs.create_job`.

        Raises
        ------
        InputError
            A pinned version: only the installed version of a plugin can be run.
        """
        if self.versions:
            kinds = ", ".join(f"{k}@{v}" for k, v in sorted(self.versions.items()))
            raise InputError(f"chain {self.text!r} pins version(s) {kinds}: only the "
                             "installed version of a plugin can be run")
        return dict(self.stages), {k: dict(v) for k, v in self.params.items()}


def _value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text  # a bare word (a mode name) is meant as text


def parse_chain(text: str, *, extra: Iterable[str] = ()) -> ChainSpec:
    """Parse a chain string (see the module docstring), plus ``extra`` items.

    Parameters
    ----------
    text : str
        ``"default"``, ``""`` or comma-separated items.
    extra : iterable of str
        More items (repeated command-line options such as ``--stage``), applied after.

    Returns
    -------
    ChainSpec

    Raises
    ------
    InputError
        An item that is neither ``KIND=PLUGIN[@VERSION]`` nor ``KIND.NAME=VALUE``, or a kind
        or parameter named twice.
    """
    stages: dict[str, str] = {}
    versions: dict[str, str] = {}
    params: dict[str, dict[str, Any]] = {}
    stripped = text.strip()
    items = [] if stripped in ("", "default") else stripped.split(",")
    for item in [*items, *extra]:
        left, sep, right = item.partition("=")
        left, right = left.strip(), right.strip()
        usage = (f"chain item {item.strip()!r}: expected KIND=PLUGIN[@VERSION] or "
                 "KIND.PARAMETER=VALUE, e.g. peaks=peaks.first-moment@3 or "
                 "peaks.bias_fraction=0.2")
        if not sep or not left or not right:
            raise InputError(usage)
        if "." in left:
            kind, _, name = left.partition(".")
            if not kind or not name:
                raise InputError(usage)
            if name in params.setdefault(kind, {}):
                raise InputError(f"chain {text!r} sets {left} twice")
            params[kind][name] = _value(right)
            continue
        plugin, at, version = right.partition("@")
        if not plugin.strip() or (at and not version.strip()):
            raise InputError(usage)
        if left in stages:
            raise InputError(f"chain {text!r} names stage {left!r} twice")
        stages[left] = plugin.strip()
        if at:
            versions[left] = version.strip()
    shown = ",".join(filter(None, [stripped if stripped != "default" else "", *extra]))
    return ChainSpec(shown or "default", stages, versions, params)


def match_path(
    rows: Sequence[ResultRow], patterns: Sequence[StepPattern]
) -> dict[str, ResultRow] | None:
    """The stored results of one acquisition made by ``patterns``: one row per stage kind.

    Parameters
    ----------
    rows : sequence of ResultRow
        Every stored result of the acquisition (or more: only parent links are followed).
    patterns : sequence of StepPattern
        From :meth:`ChainSpec.patterns`.

    Returns
    -------
    dict of str to ResultRow or None
        Per stage kind, the result on the path to the newest matching result of the last
        step; None when the chain's last stage has no stored result.
    """
    if not patterns:
        return None
    children: dict[int | None, list[ResultRow]] = {}
    for row in rows:
        children.setdefault(row.parent_id, []).append(row)
    by_id = {row.id: row for row in rows}
    frontier = [row for row in children.get(None, ()) if patterns[0].matches(row)]
    for pattern in patterns[1:]:
        frontier = [child for row in frontier for child in children.get(row.id, ())
                    if pattern.matches(child)]
        if not frontier:
            return None
    if not frontier:
        return None
    path: dict[str, ResultRow] = {}
    at: ResultRow | None = max(frontier, key=lambda r: r.id)
    for pattern in reversed(patterns):
        assert at is not None
        path[pattern.kind] = at
        at = by_id.get(at.parent_id) if at.parent_id is not None else None
    return dict(reversed(list(path.items())))


def result_rows(session: Any, acquisition_ids: Sequence[int]) -> dict[int, list[ResultRow]]:
    """Every stored result of these acquisitions, as :class:`ResultRow`, per acquisition id."""
    from sqlalchemy import select

    from rasterserver.catalog.models import StageResult

    out: dict[int, list[ResultRow]] = {a: [] for a in acquisition_ids}
    columns = (StageResult.id, StageResult.acquisition_id, StageResult.parent_id,
               StageResult.stage, StageResult.plugin, StageResult.plugin_version,
               StageResult.params_hash, StageResult.output_checksum, StageResult.store_path,
               StageResult.record_kind)
    ids = list(acquisition_ids)
    for start in range(0, len(ids), 500):  # bounded IN lists
        chunk = ids[start : start + 500]
        for values in session.execute(
            select(*columns).where(StageResult.acquisition_id.in_(chunk))
            .order_by(StageResult.id)
        ):
            row = ResultRow(*values)
            out[row.acquisition_id].append(row)
    return out


def describe_patterns(patterns: Mapping[str, Sequence[StepPattern]]) -> dict[str, list[str]]:
    """JSON-ready: per target, ``kind: plugin@version`` of each step."""
    return {target: [f"{p.kind}: {p.describe()}" for p in steps]
            for target, steps in patterns.items()}

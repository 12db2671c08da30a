"""Groups of small components that inherit a number together.

A line broken into many short pieces (lines under hair hanging over the back, whose dark
strands cut every line into dashes with steps of the peak area that the line search reads as
changes of surface) gives many components of a few lines and columns each. None of them can
read the code, and each touches the numbered trunk over a few columns only: too little for
it to inherit a number alone (``min_votes``). Together they touch it over many columns, and
they touch each other at one line spacing or by continuing each other's lines. Components
whose mutual contacts agree on their relative placement are grouped (their contacts, like
any, may be a level off across a hidden depth step: a pair whose contacts disagree among
themselves does not tie, and a group is refused when the contacts between its members, all
of them, disagree with its relative placements by more than a fifth); the group inherits a
number from its contacts with numbered components under the tests a single component meets
(enough contact columns, a share of its width, agreement), and then each member under its
own (its code must not speak against its number; the distance test).
"""

from __future__ import annotations

from collections import defaultdict, deque
from collections.abc import Mapping

import numpy as np

__all__ = ["ComponentGroup", "component_groups", "group_placement"]


class ComponentGroup:
    """Components tied by agreeing contacts, with their offsets relative to the first.

    Attributes
    ----------
    relative : dict
        ``component -> offset - offset of the group's first component``.
    disagreeing : float
        Contact weight between members that contradicts the relative offsets (a cycle
        that does not close, a pair whose contacts disagree).
    agreeing : float
        Contact weight between members that agrees with them.
    """

    def __init__(self) -> None:
        self.relative: dict[int, int] = {}
        self.disagreeing = 0.0
        self.agreeing = 0.0


def _pair_delta(weights: Mapping[int, float], max_conflict: float) -> tuple[int, float] | None:
    """The delta a pair's contacts agree on, and its weight; None when they disagree."""
    total = float(sum(weights.values()))
    if total <= 0:
        return None
    delta = max(weights, key=lambda d: weights[d])
    if weights[delta] < (1.0 - max_conflict) * total:
        return None
    return int(delta), float(weights[delta])


def component_groups(
    members: set[int],
    votes: Mapping[tuple[int, int], Mapping[int, float]],
    *,
    max_conflict: float = 0.2,
    min_weight: float = 3.0,
) -> list[ComponentGroup]:
    """Groups of ``members`` tied by contacts that agree on their relative offsets.

    Parameters
    ----------
    members : set of int
        The components that may group (those the code alone does not place).
    votes : mapping
        ``votes[(a, b)][delta]``: weight of ``offset(b) - offset(a) == delta``
        (:func:`.numbering_checks.contact_votes`, both directions).
    max_conflict : float
        A pair ties only when at least ``1 - max_conflict`` of its contact weight agrees
        on one delta.
    min_weight : float
        Least agreeing weight (contact columns) of a tie.

    Returns
    -------
    list of ComponentGroup
        Groups of two or more components, in the order of their smallest member.
    """
    ties: dict[int, list[tuple[int, int, float]]] = defaultdict(list)
    for (a, b), weights in votes.items():
        if a == b or a not in members or b not in members:
            continue
        found = _pair_delta(weights, max_conflict)
        if found is not None and found[1] >= min_weight:
            ties[a].append((b, found[0], found[1]))
    groups: list[ComponentGroup] = []
    group_of: dict[int, ComponentGroup] = {}
    for start in sorted(ties):
        if start in group_of:
            continue
        group = ComponentGroup()
        group.relative[start] = 0
        group_of[start] = group
        queue = deque([start])
        while queue:
            a = queue.popleft()
            for b, delta, _ in sorted(ties[a]):
                if b not in group.relative:
                    group.relative[b] = group.relative[a] + delta
                    group_of[b] = group
                    queue.append(b)
        if len(group.relative) > 1:
            groups.append(group)
    # Every contact between two members is judged against the relative offsets, whatever
    # its weight and whether its pair tied: a weak or split pair is evidence too.
    for (a, b), weights in votes.items():
        mine = group_of.get(a)
        if a >= b or mine is None or group_of.get(b) is not mine:
            continue
        step = mine.relative[b] - mine.relative[a]
        for delta, weight in weights.items():
            if delta == step:
                mine.agreeing += float(weight)
            else:
                mine.disagreeing += float(weight)
    return groups


def group_placement(
    group: ComponentGroup,
    votes: Mapping[tuple[int, int], Mapping[int, float]],
    partners: Mapping[int, list[int]],
    offset: Mapping[int, int],
    first_col: np.ndarray,
    last_col: np.ndarray,
    *,
    min_votes: float,
    min_contact_share: float,
    max_conflict: float,
) -> tuple[int | None, str]:
    """The offset of the group's first component implied by its numbered contacts.

    Parameters
    ----------
    group : ComponentGroup
    votes : mapping
        As for :func:`component_groups`.
    partners : mapping
        ``component -> the components it has contacts with``.
    offset : mapping
        ``component -> offset``, -1 when not numbered.
    first_col, last_col : numpy.ndarray
        Per component, its first and last column.
    min_votes, min_contact_share, max_conflict : float
        As for a single component (:func:`.line_numbering.number_lines`): least contact
        columns, least share of the group's width, largest share of contacts that
        disagree with the placement.

    Returns
    -------
    offset : int or None
        None when the group is refused.
    reason : str
        Why it was refused; empty when placed.
    """
    if group.disagreeing > max_conflict * (group.agreeing + group.disagreeing):
        return None, (
            f"grouped with {len(group.relative) - 1} touching piece(s) whose contacts "
            "disagree on their order"
        )
    implied: dict[int, float] = defaultdict(float)
    for c, rel in group.relative.items():
        for a in partners.get(c, ()):
            if offset.get(a, -1) < 0 or a in group.relative:
                continue
            for delta, weight in votes[(a, c)].items():
                implied[offset[a] + delta - rel] += float(weight)
    total = float(sum(implied.values()))
    cols = list(group.relative)
    width = int(last_col[cols].max() - first_col[cols].min() + 1)
    if total < min_votes or total < min_contact_share * width:
        return None, (
            f"grouped with {len(cols) - 1} touching piece(s), which touch numbered lines over "
            f"{total:.0f} columns only, {width} wide"
        )
    best = max(implied, key=lambda o: implied[o])
    if implied[best] < (1.0 - max_conflict) * total:
        return None, (
            f"grouped with {len(cols) - 1} touching piece(s); the numbered lines they touch "
            f"disagree on their number ({implied[best]:.0f} of {total:.0f} contact columns "
            "agree)"
        )
    return int(best), ""

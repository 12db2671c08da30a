"""Groups of small components: ties, cycles that do not close, placement from contacts."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from rasterserver_plugins.component_groups import component_groups, group_placement


def _votes(pairs: dict[tuple[int, int], dict[int, float]]) -> dict:
    """Both directions, as :func:`contact_votes` gives them."""
    votes: dict = defaultdict(lambda: defaultdict(float))
    for (a, b), weights in pairs.items():
        for delta, weight in weights.items():
            votes[(a, b)][delta] += weight
            votes[(b, a)][-delta] += weight
    return votes


def _partners(votes: dict) -> dict[int, list[int]]:
    out: dict[int, list[int]] = defaultdict(list)
    for a, b in votes:
        out[b].append(a)
    return out


def test_a_chain_of_pieces_groups_with_relative_offsets() -> None:
    votes = _votes({(1, 2): {1: 3.0}, (2, 3): {-2: 4.0}, (3, 4): {0: 2.0}})
    groups = component_groups({1, 2, 3, 4}, votes, min_weight=2.0)
    assert len(groups) == 1
    assert groups[0].relative == {1: 0, 2: 1, 3: -1, 4: -1}
    assert groups[0].disagreeing == 0.0 and groups[0].agreeing == 9.0


def test_weak_or_disagreeing_ties_do_not_group() -> None:
    # 1-2 too weak, 3-4 split between two deltas, 5 not a member
    votes = _votes({(1, 2): {0: 1.0}, (3, 4): {0: 3.0, 1: 3.0}, (4, 5): {0: 9.0}})
    assert component_groups({1, 2, 3, 4}, votes, min_weight=2.0) == []


def test_a_cycle_that_does_not_close_is_refused() -> None:
    # 1 -> 2 -> 3 says offset(3) = offset(1) + 2, the direct tie says + 1: a hidden line
    votes = _votes({(1, 2): {1: 5.0}, (2, 3): {1: 5.0}, (1, 3): {1: 5.0}, (0, 1): {0: 20.0}})
    (group,) = component_groups({1, 2, 3}, votes)
    assert group.disagreeing == 5.0
    off, why = group_placement(
        group, votes, _partners(votes), {0: 10, 1: -1, 2: -1, 3: -1},
        np.zeros(4, np.int64), np.full(4, 9, np.int64),
        min_votes=8.0, min_contact_share=0.2, max_conflict=0.2,
    )  # fmt: skip
    assert off is None and "disagree on their order" in why


def test_contacts_of_pairs_that_did_not_tie_are_judged_too() -> None:
    # 1-3 is split between two deltas (no tie), but 1 and 3 join through 2: its contacts
    # speak against the group's placement of 3 (two lines below 1) with 4 of 6 columns
    votes = _votes({(1, 2): {1: 5.0}, (2, 3): {1: 5.0}, (1, 3): {2: 2.0, 1: 4.0}})
    (group,) = component_groups({1, 2, 3}, votes)
    assert group.relative == {1: 0, 2: 1, 3: 2}
    assert (group.agreeing, group.disagreeing) == (12.0, 4.0)
    off, why = group_placement(
        group, votes, _partners(votes), {1: -1, 2: -1, 3: -1}, np.zeros(4, np.int64),
        np.full(4, 9, np.int64), min_votes=8.0, min_contact_share=0.2, max_conflict=0.2,
    )  # fmt: skip
    assert off is None and "disagree on their order" in why


def test_a_group_inherits_what_no_member_could_alone() -> None:
    # three pieces each touching numbered component 0 over 4 columns (under 8 alone)
    votes = _votes({(0, 1): {2: 4.0}, (0, 2): {3: 4.0}, (0, 3): {1: 4.0},
                    (1, 2): {1: 3.0}, (1, 3): {-1: 3.0}})  # fmt: skip
    (group,) = component_groups({1, 2, 3}, votes)
    first = np.array([0, 10, 20, 30])
    last = np.array([60, 19, 29, 39])
    off, why = group_placement(
        group, votes, _partners(votes), {0: 5, 1: -1, 2: -1, 3: -1}, first, last,
        min_votes=8.0, min_contact_share=0.2, max_conflict=0.2,
    )  # fmt: skip
    assert why == "" and off == 7
    assert {c: off + r for c, r in group.relative.items()} == {1: 7, 2: 8, 3: 6}


def test_too_little_or_disagreeing_contact_refuses_the_group() -> None:
    votes = _votes({(0, 1): {2: 3.0}, (1, 2): {1: 3.0}})
    (group,) = component_groups({1, 2}, votes)
    first, last = np.array([0, 0, 10]), np.array([9, 9, 19])
    off, why = group_placement(
        group, votes, _partners(votes), {0: 5}, first, last,
        min_votes=8.0, min_contact_share=0.2, max_conflict=0.2,
    )  # fmt: skip
    assert off is None and "over 3 columns only" in why
    # enough columns, but numbered neighbours imply two placements
    votes = _votes({(0, 1): {2: 6.0}, (9, 2): {0: 6.0}, (1, 2): {1: 3.0}})
    (group,) = component_groups({1, 2}, votes)
    off, why = group_placement(
        group, votes, _partners(votes), {0: 5, 9: 30}, np.zeros(10, np.int64),
        np.full(10, 9, np.int64), min_votes=8.0, min_contact_share=0.2, max_conflict=0.2,
    )  # fmt: skip
    assert off is None and "disagree on their number" in why


def test_no_members_no_groups() -> None:
    assert component_groups(set(), {}) == []
    assert component_groups({1}, _votes({(1, 1): {0: 5.0}})) == []

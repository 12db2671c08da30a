"""Parameter trends: changes flagged only beyond the smallest detectable change."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np

from rasterserver.trends import REPEATABILITY_SD, TrendVisit, sdc, trends, trends_csv, write_trends

DAY = dt.datetime(2024, 1, 15, tzinfo=dt.UTC)


def visits(values: list[float | None], name: str = "lateral_deviation_max_mm") -> list[TrendVisit]:
    return [
        TrendVisit(
            f"v{k}",
            DAY + dt.timedelta(days=182 * k),
            None if v is None else {name: {"value": v, "unit": "mm", "spread": None}},
        )
        for k, v in enumerate(values)
    ]


def test_sdc_is_the_95_percent_limit_of_a_difference() -> None:
    sd = REPEATABILITY_SD["surface_rotation_rms_deg"]
    assert math.isclose(sdc("surface_rotation_rms_deg"), 1.96 * math.sqrt(2) * sd)
    assert sdc("no_such_parameter") is None


def test_changes_flagged_only_beyond_the_sdc() -> None:
    limit = sdc("lateral_deviation_max_mm")
    assert limit is not None
    (row,) = trends(visits([10.0, 10.0 + 0.9 * limit, 10.0 + 2.5 * limit]))
    assert [v["flagged"] for v in row["visits"]] == [False, False, True]
    assert row["first_to_last"]["flagged"] and row["flagged"]
    assert math.isclose(row["first_to_last"]["change"], 2.5 * limit)


def test_noise_only_pairs_are_rarely_flagged_and_progression_mostly() -> None:
    rng = np.random.default_rng(14)
    sd = REPEATABILITY_SD["surface_rotation_max_deg"]
    name = "surface_rotation_max_deg"
    noise = [
        trends(visits(list(8.0 + rng.normal(0, sd, 2)), name))[0]["first_to_last"]["flagged"]
        for _ in range(400)
    ]
    assert np.mean(noise) <= 0.08
    # a true change of twice the SDC lies 1.96 SD of a difference beyond it: 97.5 % flagged
    # (3 deg, the figure, is only 1.3 SDC of this parameter: about 70 %)
    step = 2.0 * sdc(name)
    grown = [
        trends(visits([8.0 + rng.normal(0, sd), 8.0 + step + rng.normal(0, sd)], name))[0][
            "flagged"
        ]
        for _ in range(400)
    ]
    assert np.mean(grown) >= 0.95


def test_missing_visits_and_unknown_parameters() -> None:
    (row,) = trends(visits([5.0, None, 9.0]))
    assert [v["value"] for v in row["visits"]] == [5.0, None, 9.0]
    assert row["visits"][2]["change"] == 4.0  # from the last visit with a value
    (other,) = trends(visits([1.0, 100.0], name="a_new_parameter"))
    assert other["sdc"] is None and not other["flagged"]
    assert trends([]) == []


def test_files(tmp_path) -> None:
    table = trends(visits([10.0, 14.0]))
    text = trends_csv(table)
    assert text.splitlines()[0] == (
        "parameter,unit,visit,date,value,change,sdc,flagged,vp_carried_from"
    )
    assert text.splitlines()[2].endswith(",yes,")
    csv_path, json_path = write_trends(table, tmp_path)
    document = json.loads(json_path.read_text())
    assert document["format"] == "rasterserver.trends/1" and "benchmarks" in document["sd_source"]
    assert csv_path.read_text() == text


def test_a_value_measured_with_another_visits_vp_says_so() -> None:
    first, second = visits([10.0, 14.0])
    assert second.parameters is not None
    entry = dict(second.parameters["lateral_deviation_max_mm"], vp_carried_from="uid-1")
    carried = TrendVisit(second.label, second.when, {"lateral_deviation_max_mm": entry})
    (row,) = trends([first, carried])
    assert [v["vp_carried_from"] for v in row["visits"]] == [None, "uid-1"]
    assert row["visits"][1]["flagged"]  # a carried value is compared like any other
    assert trends_csv([row]).splitlines()[2].endswith(",yes,uid-1")

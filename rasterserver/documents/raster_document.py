"""The raster definition (``rasterserver.raster/1``): the diapositive's lines and their code."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import ConfigDict, Field, Strict, model_validator

from rasterserver.documents.fields import Finite, Positive, StrictDocument, fmt, refuse
from rasterserver.raster import closest_windows


class RasterCode(StrictDocument):
    """How the line kinds identify positions."""

    model_config = ConfigDict(title="code")

    window: Annotated[int, Strict(), Field(ge=1)] = Field(
        description="code window length k: the kinds of any k consecutive lines identify their "
        "absolute position (checked against the lines)"
    )
    min_distance: Annotated[int, Strict(), Field(ge=1)] = Field(
        1,
        description="minimum Hamming distance between any two windows (1: unique; 2: a single "
        "misread kind is detected, never mistaken for another position); checked",
    )


class RasterLine(StrictDocument):
    """One line of the diapositive."""

    model_config = ConfigDict(title="line")

    number: Annotated[int, Strict(), Field(ge=-(2**31), le=2**31 - 1)] = Field(
        description="absolute line number (what the line numbering stage must recover); unique"
    )
    v: Finite = Field(description="diapositive coordinate of the line centre; strictly increasing")
    kind: Literal["light", "heavy"] = Field(description="`light` or `heavy`")
    width: Positive = Field(
        description="full width of the transparent stripe in diapositive units (> 0), before "
        "projector defocus"
    )


class RasterDocument(StrictDocument):
    """A raster diapositive: its lines in order of increasing ``v`` and their code."""

    model_config = ConfigDict(title="raster definition")

    format: Literal["rasterserver.raster/1"] = Field(description="the format tag (required)")
    name: Annotated[str, Strict(), Field(min_length=1, max_length=100)] = Field(
        description="identifier; `default` is the built-in diapositive"
    )
    description: Annotated[str, Strict(), Field(max_length=10_000)] = Field(
        "", description="free text"
    )
    units: Annotated[str, Strict(), Field(max_length=200)] | None = Field(
        None,
        description="informational: positions and widths are diapositive units (the "
        "projector's `v`)",
    )
    code: RasterCode = Field(description="the code of the line kinds")
    lines: Annotated[list[RasterLine], Field(min_length=1, max_length=10_000)] = Field(
        description="one object per line, **in order of increasing `v`** (top of the back to "
        "bottom)"
    )

    @model_validator(mode="after")
    def _lines_and_code(self) -> RasterDocument:
        v = np.array([ln.v for ln in self.lines])
        if v.size > 1 and np.any(np.diff(v) <= 0):
            i = int(np.flatnonzero(np.diff(v) <= 0)[0]) + 1
            raise refuse(
                f"{fmt(v[i])} does not exceed the previous line's {fmt(v[i - 1])}: lines "
                "are listed in order of strictly increasing v",
                f"lines[{i}].v",
            )
        seen: dict[int, int] = {}
        for i, ln in enumerate(self.lines):
            if ln.number in seen:
                raise refuse(
                    f"{ln.number} is also the number of lines[{seen[ln.number]}]",
                    f"lines[{i}].number",
                )
            seen[ln.number] = i
        window, wanted = self.code.window, self.code.min_distance
        if window > len(self.lines):
            raise refuse(
                f"{window} is longer than the raster ({len(self.lines)} lines)", "code.window"
            )
        if wanted > window:
            raise refuse(f"{wanted} exceeds the window ({window})", "code.min_distance")
        bits = np.array([ln.kind == "heavy" for ln in self.lines], dtype=np.uint8)
        distance, i, j = closest_windows(bits, window)
        if distance < wanted:
            how = "are identical" if distance == 0 else f"differ in only {distance} line(s)"
            raise refuse(
                f"the windows of {window} lines starting at lines[{i}] and lines[{j}] {how}, "
                f"but min_distance is {wanted}: the kinds do not identify positions as "
                "declared",
                "code",
            )
        return self

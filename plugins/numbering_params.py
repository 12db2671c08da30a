"""The parameters of line numbering (:class:`.line_numbering.CodeWindowNumbering`): how the
code is read, when a component inherits a number, and which checks refuse what."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from rasterserver.stage import StageParams

__all__ = ["CodeWindowParams"]


class CodeWindowParams(StageParams):
    """Parameters of :class:`.line_numbering.CodeWindowNumbering` (defaults: version 8)."""

    #: the options tried as versions 26-28, off: left out of the digest at their defaults, so
    #: that adding them kept version 25's (version 29 switched ``meet_tolerance`` on, and
    #: adds ``outer_gap``, on: both are in its digest; version 30 adds ``bracket_line``, on)
    digest_omits_defaults: ClassVar[frozenset[str]] = frozenset(
        {
            "block_gain_share",
            "block_one_shift",
            "gap_departure",
            "gap_peaks",
            "course_beyond",
            "course_departure",
            "end_jump",
            "final_run",
        }
    )

    area_ratio: float | None = Field(
        None,
        gt=1,
        description="Peak-area ratio of a heavy to a light line (default: from the raster).",
    )
    tolerance: float = Field(
        0.5, gt=0, le=1, description="Departure (in log area ratios) counted as a miss."
    )
    min_lines: int | None = Field(
        None,
        ge=1,
        description="Fewest lines numbered by the code alone (window; +1 at distance 1).",
    )
    min_margin: float | None = Field(
        None,
        ge=0,
        description="Least cost margin of the best placement (default: 2, 4 at distance 1).",
    )
    max_cost_rate: float = Field(
        0.25, ge=0, description="Largest share of differences the best may miss."
    )
    poor_run_factor: float = Field(
        0.0,
        ge=0,
        description="Also refuse a run of a component's levels whose placement costs over "
        "this many times max_cost_rate per difference, a margin more than another's (0: only "
        "runs another placement reads cleanly; version 17: 2).",
    )
    min_columns: int = Field(5, ge=1, description="Columns for a difference's full weight.")
    correlation: float = Field(
        4.0, ge=1, description="Columns over which the albedo texture is correlated."
    )
    min_votes: float = Field(
        8.0, ge=1, description="Least contact columns for a component to inherit a number."
    )
    max_conflict: float = Field(
        0.2, gt=0, lt=1, description="Share of contradicting contacts that refuses."
    )
    min_conflict: float = Field(
        3.0, ge=1, description="Least contradicting contact columns that refuse."
    )
    max_depth: float = Field(
        600.0, gt=0, description="Largest distance (mm) from the calibrated back plane."
    )
    min_contact_share: float = Field(
        0.2,
        ge=0,
        le=1,
        description="Least contact columns, as a share of a component's width, to inherit.",
    )

    group_ties: float = Field(
        3.0,
        ge=0,
        description="Least contact columns that tie two small components into a group "
        "numbered together from its contacts with numbered lines (line pieces under hair); "
        "0: no groups (version 10).",
    )

    pair_agreement: float = Field(
        0.4,
        ge=0.0,
        description="Spare the shorter line of a pair contradicting the code where its pairs "
        "with its other column neighbours agree with the code (depart by less than this, in "
        "units of the log heavy/light ratio) over more columns; 0 always refuses it.",
    )
    pair_shift: bool = Field(
        True,
        description="Where a contradicting pair would agree with the code were both its "
        "lines numbered one off (a block placed off behind an albedo edge), spare its "
        "shorter line only by agreeing pairs that the same shift would contradict "
        "(false: any agreeing pair; version 21).",
    )
    shift_block: int = Field(
        20,
        ge=0,
        description="With pair_shift, refuse with such a line the lines of up to this many "
        "peaks tied to it by pairs that agree under the shift too (its block, placed off "
        "with it; 0: none; version 21: 0).",
    )
    tile_check: bool = Field(
        True,
        description="Refuse lines where the code read in their own columns contradicts "
        "their component's placement.",
    )
    tile_band: int = Field(64, ge=8, description="Width (columns) of a code band.")
    column_check: bool = Field(
        True,
        description="Refuse numbered peaks with no numbered peak above or below them.",
    )
    final_isolated: bool = Field(
        True,
        description="With column_check, refuse them again last, after the steps that "
        "refuse the peaks beside them (version 17: false).",
    )
    final_order: bool = Field(
        True,
        description="Last, before the lone peaks, refuse both peaks of every two numbered "
        "column neighbours whose numbers do not increase downwards (version 24 and before: "
        "false).",
    )
    tile_gain: float = Field(
        2.5, gt=0, description="Cost another placement must save on a band's run to refuse."
    )
    block_edge_check: bool = Field(
        True,
        description="Refuse numbered peaks directly beside a doubtful line or a peak out of "
        "column order, where no gap separates them.",
    )
    block_gap: float = Field(
        1.25,
        gt=1.0,
        description="Largest gap (line spacings) counted as directly beside.",
    )
    block_share: float = Field(
        0.5,
        ge=0.0,
        description="Refuse a peak beside a doubtful one only where doubtful peaks number "
        "this share of the numbered ones around it (0: wherever it is).",
    )
    doubtful: Literal["code", "unnumbered"] = Field(
        "unnumbered",
        description="Doubtful lines for the block-edge check: those the code refused inside "
        "numbered components (version 6) or every line left unnumbered.",
    )
    faint_ratio: float = Field(
        1.35,
        ge=1.0,
        description="A code whose heavy:light area ratio is below this is faint: it reads "
        "few small components, so only the lines it refused inside numbered components are "
        "doubtful for the block-edge check, among faint_share, and a pair's ratio contradicts "
        "it only faint_departure off (1: never; version 15).",
    )
    faint_share: float = Field(
        0.2,
        ge=0.0,
        description="block_share for a faint code (see faint_ratio).",
    )
    faint_departure: float = Field(
        1.5,
        gt=0.0,
        description="Least departure (in the code's log ratios) of a pair's intensity ratio "
        "from the code's that contradicts it, for a faint code (others: 0.75; version 16: "
        "0.75).",
    )
    island_peaks: int = Field(
        3,
        ge=0,
        description="Refuse column runs of fewer numbered lines standing alone, 2.5 "
        "spacings or more from other numbered peaks (0: keep them).",
    )
    min_run: int = Field(
        6,
        ge=0,
        description="Refuse runs of fewer numbered peaks of a line cut off by its refused "
        "peaks (0: keep them).",
    )
    end_margin: int = Field(
        3,
        ge=0,
        description="Refuse the first this many numbered peaks of a line beyond "
        "end_refused or more of its unnumbered peaks (0: keep them; version 9: 0).",
    )
    end_refused: int = Field(
        6,
        ge=1,
        description="Unnumbered peaks of a line beyond its numbered ones that make the "
        "end_margin peaks next to them doubtful.",
    )
    end_dim: float = Field(
        0.3,
        ge=0,
        lt=1,
        description="Refuse a line's end peak lower than this share of the mean height of "
        "its next six numbered peaks (0: keep it; version 9: 0).",
    )
    end_jump: float = Field(
        0.0,
        ge=0,
        description="Refuse a line's end peak this many times higher, or lower than its "
        "inverse, than the mean height of its next two numbered peaks: a step to another "
        "surface (0: keep it; an option, off: tried as version 26 with 2.8, not adopted).",
    )
    final_run: int = Field(
        0,
        ge=0,
        description="After the last steps, refuse runs of fewer numbered peaks of a line "
        "cut off by its refused peaks (0 or 1: keep them; an option, off: tried as version 26 "
        "with 2, not adopted).",
    )
    meet_tolerance: float = Field(
        1.0,
        ge=0,
        description="Refuse a line's end peak lying within this many rows of the course "
        "of another numbered line, of another number, that ends in the next column beyond "
        "it: the meeting of two surfaces' lines (0: keep it; versions 25-28: 0; tried alone "
        "as version 26, not adopted; adopted with outer_gap in version 29).",
    )
    course_beyond: float = Field(
        0.0,
        ge=0,
        description="Refuse a line's numbered end peaks (up to three, from the outermost) "
        "lying within this many rows of the straight course of the line's unnumbered peaks "
        "beyond them and course_departure rows or more off its own numbered peaks' course: "
        "the line turns there onto another surface (0: keep them; an option, off: tried as "
        "version 27 with 0.4, not adopted).",
    )
    course_departure: float = Field(
        1.0,
        gt=0,
        description="Least distance (rows) of such an end peak from the straight course of "
        "its line's numbered peaks farther in (with course_beyond).",
    )
    edge_run: int = Field(
        6,
        ge=0,
        description="Refuse up to this many peaks at a line's end where it leaves the "
        "frame's top or bottom edge, outermost in their columns within edge_reach line "
        "spacings of the edge (0: keep them; version 11: 0).",
    )
    edge_reach: float = Field(
        1.5,
        gt=0,
        description="How near the frame's edge, in line spacings, a column's outermost "
        "numbered peak is left unconfirmed on that side (a line beyond it would be cut).",
    )
    edge_company: int = Field(
        3,
        ge=0,
        description="Refuse a line's end at the frame's edge only where this many unnumbered "
        "peaks lie beyond it, toward the frame's inside, within two line spacings (0: "
        "wherever it is).",
    )
    surround_share: float = Field(
        0.4,
        ge=0,
        lt=1,
        description="Refuse the peaks near a long line's end where unnumbered peaks are at "
        "least this share of all the peaks within two line spacings (a line carried onto "
        "a refused surface; 0: keep them; version 12: 0).",
    )
    surround_reach: int = Field(
        8,
        ge=0,
        description="The numbered peaks at each end of a line judged by surround_share.",
    )
    surround_length: int = Field(
        80,
        ge=0,
        description="Least numbered peaks of a line whose ends surround_share judges (dashes "
        "in hair end at strands, not at a surface's edge).",
    )
    surround_passes: int = Field(
        3,
        ge=1,
        description="Times surround_share judges the ends, each among the peaks the pass "
        "before left (a piece on a refused surface erodes, a line's end on the skin stays).",
    )
    skip_ratio: float = Field(
        1.9,
        ge=0,
        description="Last, refuse column neighbours numbered n and n + 1 lying this many "
        "times the single gaps beside them apart (a line skipped between them, as on a dark "
        "cloth that shows the heavy lines only; 0: keep them; version 13: 0).",
    )
    skip_line_peaks: int = Field(
        3,
        ge=0,
        description="A line with this many peaks refused by skip_ratio is refused whole "
        "(its number is one for all its columns; 0: never).",
    )
    skip_line_share: float = Field(
        0.2,
        ge=0,
        le=1,
        description="Least share of a line's numbered peaks that skip_line_peaks must make up.",
    )
    detached_peaks: int = Field(
        100,
        ge=0,
        description="Last, refuse the numbered pieces of at most this many peaks that no "
        "standing contact joins to the frame's largest numbered block (their number rested "
        "on contacts refused since, or across a depth or brightness step, as below a "
        "waistband; 0: keep them; version 14: 0).",
    )
    detached_gap_low: float = Field(
        0.6,
        gt=0,
        description="Least gap of column neighbours numbered n and n + 1, in medians of the "
        "single gaps beside them, that joins them into one block (detached_peaks).",
    )
    detached_gap_high: float = Field(
        1.6,
        gt=0,
        description="Largest such gap that joins them (detached_peaks).",
    )
    detached_brightness: float = Field(
        1.0,
        gt=0,
        description="Largest departure of column neighbours' log area ratio from the code's "
        "at their numbers that joins them (a material's edge changes it by more).",
    )
    reading_run: int = Field(
        6,
        ge=0,
        description="Last, read a numbered peak's column on through up to this many "
        "unnumbered peaks beyond it, one spacing apart, and refuse the peak where the code "
        "read there places it a line or two off (a line's end run onto a cloth that shows "
        "the next raster line at its row; 0: none; version 18: 0).",
    )
    reading_least: int = Field(
        3,
        ge=1,
        description="Least brightness ratios of consecutive peaks that reading_run reads.",
    )
    reading_margin: float = Field(
        0.3,
        ge=0,
        description="Least advantage, per ratio (natural log), of the best shifted reading "
        "over the peak's own number (reading_run).",
    )
    reading_clean: float = Field(
        0.2,
        gt=0,
        description="Largest departure, per ratio (natural log), of the shifted reading "
        "from the code (reading_run).",
    )
    block_least: int = Field(
        15,
        ge=0,
        description="Before the line-end steps, refuse blocks of at least this many numbered "
        "peaks, joined along their lines and columns and holding a line's end, whose column "
        "neighbours' brightness ratios read the code a line or two off their numbers (a "
        "cloth standing off by a line's depth, its lines numbered with the back's; 0: none; "
        "version 19: 0).",
    )
    block_gain: float = Field(
        0.3,
        ge=0,
        description="Least advantage, per ratio (natural log), of a shifted reading over a "
        "peak's own numbers for it to join such a block (block_least).",
    )
    block_gain_share: float = Field(
        0.0,
        ge=0,
        description="When above 0, block_gain is replaced by this share of the code's "
        "contrast, the log ratio of its heavy to its light line widths (a faint 45:55 code "
        "differs by 0.20 only, below block_gain 0.3; block_least; 0: block_gain as given).",
    )
    block_one_shift: bool = Field(
        False,
        description="Join into such a block only peaks whose ratios read the code off by "
        "one and the same shift (a cloth's lines are off together; noise reads mixed "
        "shifts; block_least).",
    )
    block_ends: int = Field(
        2,
        ge=1,
        description="Fewest lines whose end (first or last numbered peak) such a block "
        "holds (block_least): a cloth is met where several lines leave the skin.",
    )
    block_clean: float = Field(
        0.15,
        gt=0,
        description="Largest departure, per ratio (natural log), of that shifted reading "
        "from the code (block_least).",
    )
    linked_one_sided: int = Field(
        50,
        ge=0,
        description="Last, refuse components of at most this many numbered peaks that "
        "inherited their numbers and are touched by numbered lines on one side only (0: "
        "none; version 22: 0).",
    )
    kink_bend: float = Field(
        0.0,
        ge=0,
        description="Last, before the lone peaks, refuse a line's first or last numbered peak "
        "lying more than this many rows off the straight course of the two before it (and "
        "kink_ratio times the line's own bends) where the lines numbered either side do not "
        "go on beyond it (a link onto another surface's line; 0: none; 0.8 was tried as "
        "version 24 and not adopted).",
    )
    outer_gap: float = Field(
        1.2,
        ge=0,
        description="Last, before the lone peaks, refuse a line's numbered end peaks (up to "
        "three, from the outermost) that have no peak on one side in their column and lie "
        "more than this many times farther from the next peak on the other side than the "
        "line's next four numbered peaks do (the line runs onto another surface at a depth "
        "step; 0: none; versions 25-28: 0).",
    )
    gap_peaks: int = Field(
        0,
        ge=0,
        description="Last, with the one-sided lines, refuse lines of at most this many "
        "numbered peaks whose numbered peaks lie (median) gap_departure or more line "
        "spacings off a whole count from their numbered column neighbours (numbered across "
        "a depth step the image cannot count; 0: none; an option, off: screened with 20, "
        "not yet judged on held-out frames).",
    )
    gap_departure: float = Field(
        0.4,
        gt=0,
        le=0.5,
        description="Least median departure from a whole count of spacings (gap_peaks).",
    )
    kink_ratio: float = Field(
        5.0,
        gt=0,
        description="How many times the median second difference of the rows of the line's "
        "five numbered peaks before the end the bend must exceed (kink_bend).",
    )
    one_sided_peaks: int = Field(
        6,
        ge=0,
        description="Last, before the lone peaks, refuse lines of at most this many numbered "
        "peaks none of which has numbered peaks directly above and below it (numbered by "
        "one neighbour's contact across what may be a depth step; 0: none; version 20: 0; "
        "versions 21-28: 5).",
    )
    bracket_run: int = Field(
        8,
        ge=0,
        description="Last, number runs of up to this many unnumbered peaks lying one line "
        "spacing apart between numbered peaks of their column (0: none).",
    )
    bracket_line: bool = Field(
        True,
        description="Leave a bracketed run unnumbered when one of its peaks lies on a line "
        "whose numbered peaks carry another number (a hidden line and a spurious peak make "
        "the count add up one line off; false: number it, version 29).",
    )
    bracket_tolerance: float = Field(
        0.2,
        gt=0,
        lt=0.5,
        description="Largest departure of a bracketed run's gaps from one line spacing "
        "(share of the spacing).",
    )

    @model_validator(mode="after")
    def _gaps_ordered(self) -> CodeWindowParams:
        if 0 < self.end_jump <= 1:
            # a factor of 1 or less would call every end a step
            raise ValueError(f"end_jump must be 0 (off) or more than 1, got {self.end_jump}")
        # an empty range would join no column pair and detach every piece off the lines
        if self.detached_gap_low >= self.detached_gap_high:
            raise ValueError(
                f"detached_gap_low ({self.detached_gap_low}) must be less than "
                f"detached_gap_high ({self.detached_gap_high})"
            )
        return self

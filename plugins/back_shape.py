"""Back-shape analysis stage (placeholder: replaced by the analysis of issue 12)."""

from __future__ import annotations

from typing import ClassVar

from rasterserver.records_analysis import BackShape
from rasterserver.records_surface import Surface
from rasterserver.stage import Stage, StageContext, StageParams


class BackShapeAnalysis(Stage[Surface, BackShape]):
    """Curvature, landmarks, symmetry line, midline and clinical parameters of a back."""

    name: ClassVar[str] = "analysis.back-shape"
    stage: ClassVar[str] = "analysis"
    version: ClassVar[str] = "0"
    input_type = Surface
    output_type = BackShape
    requires: ClassVar[tuple[str, ...]] = ("calibration",)

    def run(self, data: Surface, params: StageParams, context: StageContext) -> BackShape:
        """Not implemented yet."""
        return BackShape.empty("the back-shape analysis is not implemented yet")

"""Importers of other instruments' data: each writes a setup and an image set that
``pmdsim evaluate`` takes as they are (docs/architecture.md, "Where new things go")."""

from .sofast import (
    SofastImportError,
    SofastImportSummary,
    fraction_to_pattern_mm,
    fraction_to_screen_mm,
    import_sofast,
    pattern_mm_to_fraction,
    sofast_screen_transform,
)

__all__ = ["SofastImportError", "SofastImportSummary", "import_sofast", "sofast_screen_transform", "fraction_to_pattern_mm",
           "pattern_mm_to_fraction", "fraction_to_screen_mm"]

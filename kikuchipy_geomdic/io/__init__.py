"""Files: a geometry in every vendor's pattern-centre convention, detector
files, run summaries, atomic writes.

:mod:`~kikuchipy_geomdic.io.conventions` (PC conventions, records,
detector files), :mod:`~kikuchipy_geomdic.io.summary` (calibration
summaries) and :mod:`~kikuchipy_geomdic.io.files` (atomic writes, CSV
text); their main functions are exported here.

Layer 2 (io): may import :mod:`kikuchipy_geomdic.geometry` only.
"""

from kikuchipy_geomdic.io.conventions import (
    CONVENTIONS,
    convention_name,
    export_geometry,
    import_geometry,
    load_detector,
    pc_in_convention,
    save_detector,
)
from kikuchipy_geomdic.io.summary import (
    format_summary,
    geometry_from_summary,
    read_summary,
    summary_from_result,
    write_summary,
)

__all__ = [
    "CONVENTIONS",
    "convention_name",
    "export_geometry",
    "format_summary",
    "geometry_from_summary",
    "import_geometry",
    "load_detector",
    "pc_in_convention",
    "read_summary",
    "save_detector",
    "summary_from_result",
    "write_summary",
]

"""Files: a geometry in every vendor's pattern-centre convention, detector
files, run summaries, atomic writes.

Layer 2: may import :mod:`kikuchipy_geomdic.geometry` only.
"""

from kikuchipy_geomdic.io.conventions import (
    CONVENTIONS,
    convention_name,
    export_geometry,
    format_summary,
    geometry_from_summary,
    import_geometry,
    load_detector,
    pc_in_convention,
    read_summary,
    save_detector,
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

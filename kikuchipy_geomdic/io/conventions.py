"""Export and import of a calibrated geometry in every PC convention.

A calibrated geometry is only useful if it reaches the software that
indexes the map, and every vendor describes the projection centre (PC)
differently. This module writes and reads the geometry in the conventions
kikuchipy knows -- Bruker, EDAX TSL, Oxford Instruments and EMsoft (v4
and v5) -- using kikuchipy's own conversions
(:meth:`~kikuchipy.detectors.EBSDDetector.pc_tsl`,
:meth:`~kikuchipy.detectors.EBSDDetector.pc_oxford`,
:meth:`~kikuchipy.detectors.EBSDDetector.pc_emsoft` and
``EBSDDetector(..., convention=...)``), so that nothing here can disagree
with kikuchipy.

Two forms are written:

- *Records*: plain dicts (JSON-ready) with one PC in a convention, the
  detector angles, the detector shape, pixel size and binning, the
  convention and the kikuchipy version
  (:func:`export_geometry` / :func:`import_geometry`).
- *Detector files*: kikuchipy's own text format
  (:meth:`~kikuchipy.detectors.EBSDDetector.save` /
  :meth:`~kikuchipy.detectors.EBSDDetector.load`), one PC per map point,
  written with 17 significant digits so that a round trip is exact to
  float64 precision (kikuchipy's default of 7 decimals is not)
  (:func:`save_detector` / :func:`load_detector`).

Detector files are written atomically
(:func:`~kikuchipy_geomdic.io.files.atomic_write_text`): a reader sees the
old file or the complete new one. :mod:`kikuchipy_geomdic.io.summary`
describes a whole calibration, with the geometry in every convention.

Angles
------
The detector angles (``tilt``, ``azimuthal``, ``twist``, ``sample_tilt``,
degrees) are kikuchipy's: they do not depend on the PC convention, and
every record and file carries all four. Each record also lists the
vendor's own field names for the values *as kikuchipy's readers interpret
them* (e.g. EDAX "Camera Elevation Angle" is kikuchipy's ``tilt``) and,
under ``"not_in_vendor_fields"``, the non-zero angles a vendor file read
by kikuchipy would lose.

The sign of ``azimuthal`` flipped between kikuchipy 0.11 and 0.12. Every
record and file states the kikuchipy version that wrote it; importing one
written by kikuchipy < 0.12 flips the sign (with a warning), so the same
physical geometry comes back.

Layer 2 (io): may import geometry.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import kikuchipy
import numpy as np
from kikuchipy.detectors import EBSDDetector

from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.io.files import _atomic

__all__ = [
    "CONVENTIONS",
    "convention_name",
    "pc_in_convention",
    "export_geometry",
    "import_geometry",
    "save_detector",
    "load_detector",
    "read_detector_header",
]

#: The PC conventions, canonical names.
CONVENTIONS = ("bruker", "tsl", "oxford", "emsoft4", "emsoft5")

_ALIASES = {
    "bruker": "bruker",
    "tsl": "tsl",
    "edax": "tsl",
    "amatek": "tsl",
    "oxford": "oxford",
    "aztec": "oxford",
    "emsoft": "emsoft5",
    "emsoft5": "emsoft5",
    "emsoft4": "emsoft4",
}

_PC_NAMES = {
    "bruker": ("PCx", "PCy", "PCz"),
    "tsl": ("x*", "y*", "z*"),
    "oxford": ("PCx", "PCy", "DD"),
    "emsoft4": ("xpc", "ypc", "L"),
    "emsoft5": ("xpc", "ypc", "L"),
}

_PC_UNITS = {
    "bruker": (
        "fraction of width, from the left",
        "fraction of height, from the top",
        "fraction of height",
    ),
    "tsl": (
        "fraction of width, from the left",
        "fraction of height, from the bottom",
        "fraction of min(width, height)",
    ),
    "oxford": (
        "fraction of width, from the left",
        "fraction of width, from the bottom",
        "fraction of width",
    ),
    "emsoft4": (
        "unbinned px, -width * binning * (1/2 - PCx)",
        "unbinned px, height * binning * (1/2 - PCy)",
        "um, height * binning * px_size * PCz",
    ),
    "emsoft5": (
        "unbinned px, width * binning * (1/2 - PCx)",
        "unbinned px, height * binning * (1/2 - PCy)",
        "um, height * binning * px_size * PCz",
    ),
}

_ANGLES = ("tilt", "azimuthal", "twist", "sample_tilt")


# --------------------------------------------------------------------- #
# Conventions and records
# --------------------------------------------------------------------- #


def convention_name(name: str) -> str:
    """Return the canonical name of a PC convention.

    Parameters
    ----------
    name
        A convention or alias kikuchipy accepts ("bruker", "tsl", "edax",
        "amatek", "oxford", "aztec", "emsoft", "emsoft4", "emsoft5"),
        case-insensitive.

    Returns
    -------
    name
        One of :data:`CONVENTIONS` ("emsoft" is "emsoft5", as in
        kikuchipy).

    Examples
    --------
    >>> from kikuchipy_geomdic.io.conventions import convention_name
    >>> convention_name("EDAX"), convention_name("emsoft")
    ('tsl', 'emsoft5')
    """
    try:
        return _ALIASES[str(name).lower()]
    except KeyError:
        raise ValueError(
            f"Unknown PC convention {name!r}; choose from {sorted(_ALIASES)}"
        ) from None


def pc_in_convention(detector: EBSDDetector, convention: str) -> np.ndarray:
    """Return the detector's PCs in a convention, by kikuchipy's methods.

    Parameters
    ----------
    detector
        Any kikuchipy detector.
    convention
        See :func:`convention_name`.

    Returns
    -------
    pc
        Array of the shape of ``detector.pc``.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.io.conventions import pc_in_convention
    >>> det = EBSDDetector((60, 80), pc=(0.4, 0.2, 0.6), px_size=59.2, binning=8)
    >>> pc_in_convention(det, "emsoft4").round(1).tolist()
    [[-64.0, 144.0, 17049.6]]
    """
    conv = convention_name(convention)
    if conv == "bruker":
        return detector.pc_bruker().copy()
    if conv == "tsl":
        return detector.pc_tsl()
    if conv == "oxford":
        return detector.pc_oxford()
    return detector.pc_emsoft(int(conv[-1]))


#: Per convention: the vendor's names of the PC's three values, as
#: kikuchipy's readers map them, then of the angles and detector values
#: the vendor's files carry, each with how to get it from a detector.
_VENDOR_FIELDS = {
    "bruker": (
        ("PCX", "PCY", "DD"),
        {"CameraTilt": lambda d: d.tilt, "Sample Tilt": lambda d: d.sample_tilt},
    ),
    "tsl": (
        ("x-star", "y-star", "z-star"),
        {
            "Camera Elevation Angle": lambda d: d.tilt,
            "Camera Azimuthal Angle": lambda d: d.azimuthal,
            "Sample Tilt": lambda d: d.sample_tilt,
        },
    ),
    "oxford": (
        ("Pattern Center X", "Pattern Center Y", "Detector Distance"),
        {
            "Tilt Angle (rad)": lambda d: math.radians(d.sample_tilt),
            "Detector Orientation Euler Phi (rad)": lambda d: math.radians(d.tilt + 90),
        },
    ),
    "emsoft": (
        ("xpc", "ypc", "L"),
        {
            "thetac": lambda d: d.tilt,
            "delta": lambda d: float(d.px_size),
            "binning": lambda d: float(d.binning),
            "numsx": lambda d: int(d.ncols),
            "numsy": lambda d: int(d.nrows),
        },
    ),
}

#: The angles each convention's fields carry.
_CARRIED = {
    "bruker": ("tilt", "sample_tilt"),
    "tsl": ("tilt", "azimuthal", "sample_tilt"),
    "oxford": ("tilt", "sample_tilt"),
    "emsoft": ("tilt",),
}


def _vendor_fields(conv: str, pc, det: EBSDDetector) -> tuple[dict, list[str]]:
    """The vendor's field names for the values, as kikuchipy's readers
    map them, and the non-zero angles those fields do not carry."""
    key = "emsoft" if conv.startswith("emsoft") else conv
    names, extra = _VENDOR_FIELDS[key]
    fields = dict(zip(names, (float(v) for v in pc)))
    fields.update({name: get(det) for name, get in extra.items()})
    lost = [a for a in _ANGLES if a not in _CARRIED[key] and getattr(det, a) != 0]
    return fields, lost


def export_geometry(
    geometry: EBSDDetector | MapGeometry, convention: str = "bruker"
) -> dict[str, Any]:
    """Return one PC and the detector angles in a convention, as a record.

    Parameters
    ----------
    geometry
        A detector with a single PC, or a
        :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry` (its PC at its
        reference map position is exported).
    convention
        See :func:`convention_name`.

    Returns
    -------
    record
        JSON-ready dict: ``convention``, ``pc`` (3 floats), ``pc_names``,
        ``pc_units``, the four angles in degrees (kikuchipy's definitions),
        ``shape``, ``px_size``, ``binning``, ``vendor_fields``,
        ``not_in_vendor_fields`` and ``kikuchipy_version``.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.io.conventions import export_geometry
    >>> det = EBSDDetector((60, 80), pc=(0.4, 0.2, 0.6), tilt=3, azimuthal=1)
    >>> rec = export_geometry(det, "tsl")
    >>> rec["pc"], rec["vendor_fields"]["Camera Elevation Angle"]
    ([0.4, 0.8, 0.6], 3.0)
    """
    conv = convention_name(convention)
    if isinstance(geometry, MapGeometry):
        det = geometry.detector(points=np.array([geometry.reference]))
    elif isinstance(geometry, EBSDDetector):
        det = geometry
    else:
        raise TypeError(
            f"geometry must be an EBSDDetector or a MapGeometry, not {type(geometry).__name__}"
        )
    if det.navigation_size != 1:
        raise ValueError(
            f"The detector has {det.navigation_size} PCs; export one (e.g. "
            "MapGeometry's reference PC) or save all with save_detector()"
        )
    pc = pc_in_convention(det, conv).reshape(3)
    fields, lost = _vendor_fields(conv, pc, det)
    return {
        "convention": conv,
        "pc": [float(v) for v in pc],
        "pc_names": list(_PC_NAMES[conv]),
        "pc_units": list(_PC_UNITS[conv]),
        **{a: float(getattr(det, a)) for a in _ANGLES},
        "angle_units": "deg (kikuchipy's definitions)",
        "shape": [int(n) for n in det.shape],
        "px_size": float(det.px_size),
        "binning": float(det._binning),
        "vendor_fields": fields,
        "not_in_vendor_fields": lost,
        "kikuchipy_version": kikuchipy.__version__,
    }


def _version_tuple(version: str | None) -> tuple[int, ...] | None:
    if not version:
        return None
    m = re.match(r"^\s*(\d+)\.(\d+)", str(version))
    return (int(m.group(1)), int(m.group(2))) if m else None


def _azimuthal_from(value: float, version: str | None) -> float:
    """Return kikuchipy >= 0.12's azimuthal for a value written by *version*."""
    v = _version_tuple(version)
    if v is not None and v < (0, 12) and value != 0:
        warnings.warn(
            f"The geometry was written by kikuchipy {version}, before the sign of "
            f"azimuthal flipped (0.12): azimuthal {value} is read as {-value}",
            UserWarning,
            stacklevel=3,
        )
        return -float(value)
    return float(value)


def import_geometry(record: Mapping[str, Any]) -> EBSDDetector:
    """Return the detector a record of :func:`export_geometry` describes.

    Parameters
    ----------
    record
        Dict with ``convention``, ``pc``, the four angles, ``shape``,
        ``px_size``, ``binning`` and optionally ``kikuchipy_version``
        (records written by kikuchipy < 0.12 have their azimuthal sign
        flipped, with a warning).

    Returns
    -------
    detector
        :class:`~kikuchipy.detectors.EBSDDetector` with one PC (stored, as
        always in kikuchipy, in the Bruker convention).

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.io.conventions import export_geometry, import_geometry
    >>> det = EBSDDetector((60, 80), pc=(0.4, 0.2, 0.6), px_size=70, binning=8)
    >>> new = import_geometry(export_geometry(det, "emsoft4"))
    >>> bool(abs(new.pc - det.pc).max() < 1e-12)
    True
    """
    missing = [k for k in ("convention", "pc", "shape") if k not in record]
    if missing:
        raise ValueError(f"The geometry record lacks {missing}")
    conv = convention_name(record["convention"])
    pc = np.asarray(record["pc"], dtype=np.float64)
    if pc.shape[-1:] != (3,) or not np.isfinite(pc).all():
        raise ValueError(f"The record's PC {record['pc']} is not three finite numbers")
    angles = {a: float(record.get(a, 70.0 if a == "sample_tilt" else 0.0)) for a in _ANGLES}
    angles["azimuthal"] = _azimuthal_from(angles["azimuthal"], record.get("kikuchipy_version"))
    return EBSDDetector(
        shape=tuple(int(n) for n in record["shape"]),
        px_size=float(record.get("px_size", 1.0)),
        binning=float(record.get("binning", 1.0)),
        pc=pc,
        convention=conv,
        **angles,
    )


# --------------------------------------------------------------------- #
# Detector files (kikuchipy's text format)
# --------------------------------------------------------------------- #


def save_detector(detector: EBSDDetector, path: str | Path, convention: str = "bruker") -> Path:
    """Write a detector in kikuchipy's text format, exactly and atomically.

    Uses :meth:`~kikuchipy.detectors.EBSDDetector.save` (its header records
    shape, pixel size, binning, the four angles, the convention, the
    navigation shape and the kikuchipy version) with 17 significant digits
    per PC value, so :func:`load_detector` gives the detector back to
    float64 precision.

    Parameters
    ----------
    detector
        Detector with one PC or a PC per map point.
    path
        Text file to write (``.txt``).
    convention
        PC convention of the file, see :func:`convention_name`.

    Returns
    -------
    path

    Examples
    --------
    >>> import tempfile, os
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.io.conventions import save_detector, load_detector
    >>> det = EBSDDetector((60, 60), pc=(0.51, 0.27, 0.62), tilt=2, px_size=70, binning=8)
    >>> path = os.path.join(tempfile.mkdtemp(), "detector_oxford.txt")
    >>> new = load_detector(save_detector(det, path, "oxford"))
    >>> bool(abs(new.pc - det.pc).max() < 1e-15), new.tilt
    (True, 2.0)
    """
    conv = convention_name(convention)
    with _atomic(path) as tmp:
        # "%.17g" round-trips every float64; kikuchipy's "%.7f" does not
        detector.save(tmp, convention=conv, fmt="%.17g")
    return Path(path)


def read_detector_header(path: str | Path) -> dict[str, str]:
    """Return the ``key: value`` lines of a kikuchipy detector file header.

    Parameters
    ----------
    path
        File written by :meth:`~kikuchipy.detectors.EBSDDetector.save`.

    Returns
    -------
    header
        ``{key: value}`` as text, e.g. ``"convention"``,
        ``"kikuchipy version"``, ``"navigation_shape"``.
    """
    header = {}
    with open(path, encoding="utf-8") as f:
        for line in f:
            if not line.startswith("#"):
                break
            m = re.match(r"^#\s*([\w\- ]+?):\s*(.*)$", line.rstrip("\n"))
            if m:
                header[m.group(1).strip()] = m.group(2).strip()
    return header


def load_detector(path: str | Path) -> EBSDDetector:
    """Read a detector file of kikuchipy's text format.

    Uses :meth:`~kikuchipy.detectors.EBSDDetector.load`, which converts
    the PCs from the file's convention to Bruker's. Files written by
    kikuchipy < 0.12 have their azimuthal sign flipped (with a warning).

    Parameters
    ----------
    path
        File written by :func:`save_detector` or
        :meth:`~kikuchipy.detectors.EBSDDetector.save`.

    Returns
    -------
    detector

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If the file is not a readable detector file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No detector file {str(path)!r}")
    header = read_detector_header(path)
    if "shape" not in header or "convention" not in header:
        raise ValueError(f"{str(path)!r} is not a kikuchipy detector file (no header)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            det = EBSDDetector.load(path)
    except Exception as e:  # numpy/kikuchipy parsing errors of all kinds
        raise ValueError(f"Cannot read detector file {str(path)!r}: {e}") from None
    nav = header.get("navigation_shape", "")
    shape = tuple(int(n) for n in re.findall(r"\d+", nav))
    if shape and int(np.prod(shape)) == det.navigation_size and len(shape) > 1:
        det.pc = det.pc.reshape(shape + (3,))
    if not np.isfinite(det.pc).all():
        raise ValueError(f"Detector file {str(path)!r} has non-finite PCs")
    det.azimuthal = _azimuthal_from(det.azimuthal, header.get("kikuchipy version"))
    return det

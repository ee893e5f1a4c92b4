"""Check (not the package's behaviour): tutorial 03's map for a seed,
calibrated from users' starts with the crystal model, then reindexed on
the static- and dynamic-divided patterns from the users' or the true
orientations at the calibrated or the true detector: right, flagged and
wrong without a flag per row, and the calibration's time
(``results/crystal/tutorial03_seeds_*.log``).

Usage::

    python benchmarks/experiments/tutorial03_seeds.py 0   # seed, then dose (150)
"""

import contextlib
import io
import sys
import time
import warnings

import numpy as np

import kikuchipy_geomdic  # noqa: F401 (registers EBSD.refine_geometry_dic)
from kikuchipy_geomdic.indexing.reindex import reindex
from kikuchipy_geomdic.indexing.variants import domain_labels, variant_operators
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import Camera

warnings.filterwarnings("ignore")
seed = int(sys.argv[1]) if len(sys.argv) > 1 else 0
dose = int(sys.argv[2]) if len(sys.argv) > 2 else 150
mp = master_patterns.master_pattern("BaTiO3")
ops = variant_operators()
NAV = (10, 10)
MAP = dict(orientations="stripes", shape=(120, 120), orientation_error=1.0, seed=seed)


def q():
    return contextlib.redirect_stdout(io.StringIO())


with q(), contextlib.redirect_stderr(io.StringIO()):
    sm = synthetic.synthetic_map(
        mp, NAV, camera=Camera(dose=dose, static=False), start="indexed", **MAP
    )
    sm_raw = synthetic.synthetic_map(
        mp, NAV, camera=Camera(dose=dose, static=False, dynamic=False), start="uncentred", **MAP
    )
raw = sm_raw.signal
sig_re = raw.deepcopy()
sig_re.remove_static_background("divide", show_progressbar=False)
sig_re.remove_dynamic_background("divide", show_progressbar=False)
sig_cal = sm.signal
truth = sm.xmap.prop["variant"]
parent = domain_labels(sm.xmap).parent
t_cal = time.perf_counter()
with q(), contextlib.redirect_stderr(io.StringIO()):
    res = sig_cal.refine_geometry_dic(
        sm.start_xmap,
        sm.start_detector,
        mp,
        sm.energy,
        pseudo_symmetry_ops=ops[1:],
        orientation_model="crystal",
        show_progressbar=False,
    )
true = sm.geometry.as_dict()
print(
    "PC err",
    {n: f"{res.parameters[n] - true[n]:+.1e}" for n in ("pcx", "pcy", "pcz")},
    "angles",
    {n: f"{res.parameters[n] - true[n]:+.2f}" for n in ("tilt", "azimuthal", "sample_tilt")},
    f"calibrated in {time.perf_counter() - t_cal:.1f} s",
)

rows = [
    ("cal det, user starts", sm.start_xmap, res.detector),
    ("cal det, true starts", sm.xmap, res.detector),
    ("true det, user starts", sm.start_xmap, sm.detector),
    ("true det, true starts", sm.xmap, sm.detector),
]
for label, start, det in rows:
    t = time.perf_counter()
    out = reindex(
        sig_re, start, det, mp, sm.energy, pseudo_symmetry_ops=ops[1:], show_progressbar=False
    )
    dom = domain_labels(out, parent=parent).label
    right = dom == truth
    fl = out.converged == 0
    sigz = out.prop["variant_significance"]
    print(
        f"{label:<28} right {right.mean():.0%} flagged {fl.sum():3d} "
        f"wrong-unflagged {(~right & ~fl).sum()} sig med {np.median(sigz):.2f} "
        f"flagged idx {np.flatnonzero(fl).tolist()} {time.perf_counter() - t:.0f}s",
        flush=True,
    )

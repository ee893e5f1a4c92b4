"""Tutorial 03's map (BaTiO3 stripe domains, 10 x 10 over 500 um, 120 px,
150 counts/px, static and dynamic background removal, de-ebsd master
pattern, users' starts: a random variant per point refined by kikuchipy at
the start geometry) calibrated with the free and the crystal orientation
models, then reindexed with the variant operators at the calibrated
detector; per seed: largest PC error, its ratio to the standard error,
points in their right variant, flagged, wrong without a flag.

    python benchmarks/experiments/tutorial03_models.py 0   # the seed; ~1 min
"""

import contextlib
import io
import sys
import time
import warnings

from kikuchipy_geomdic.indexing.reindex import reindex
from kikuchipy_geomdic.indexing.variants import domain_labels, variant_operators
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import Camera

warnings.filterwarnings("ignore")
mp = master_patterns.master_pattern("BaTiO3")
ops = variant_operators()
seed = int(sys.argv[1]) if len(sys.argv) > 1 else 0
with contextlib.redirect_stdout(io.StringIO()):
    sm = synthetic.synthetic_map(
        mp,
        (10, 10),
        orientations="stripes",
        shape=(120, 120),
        camera=Camera(dose=150),
        start="indexed",
        orientation_error=1.0,
        seed=seed,
    )
truth = sm.xmap.prop["variant"]
parent = domain_labels(sm.xmap).parent
for model in ("free", "crystal"):
    t = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        res = sm.signal.refine_geometry_dic(
            sm.start_xmap,
            sm.start_detector,
            mp,
            sm.energy,
            pseudo_symmetry_ops=ops[1:],
            orientation_model=model,
            show_progressbar=False,
        )
        out = reindex(
            sm.signal,
            sm.start_xmap,
            res.detector,
            mp,
            sm.energy,
            pseudo_symmetry_ops=ops[1:],
            show_progressbar=False,
        )
    lab = domain_labels(out, parent=parent).label
    right = lab == truth
    flagged = out.converged == 0
    tr = sm.geometry.as_dict()
    err = max(abs(res.parameters[n] - tr[n]) for n in ("pcx", "pcy", "pcz"))
    z = max(abs(res.parameters[n] - tr[n]) / res.standard_errors[n] for n in ("pcx", "pcy", "pcz"))
    print(
        f"seed {seed} {model:7} PC err {err:.1e} z {z:.1f} right {right.mean():.0%} "
        f"flagged {flagged.mean():.0%} "
        f"wrong unflagged {(~right & ~flagged).sum()} ({time.perf_counter() - t:.0f} s)",
        flush=True,
    )

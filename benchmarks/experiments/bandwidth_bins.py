"""Is the pcz bias of section 1's EMsoft-data maps a band-width mismatch?
(issue 54; a diagnosis, the package unchanged)

Section 1's ``emsoft-data`` maps (``bench_realistic.realistic_map``: 11 x 11
Ni points of 96 px, 150 counts/px, background removed, users' indexed
starts) are projected from kikuchipy's EMsoft Ni master pattern (20 kV
bin) and calibrated with the package's ``Ni_dynamical.npz``: ebsdsim's
per-bin master patterns 20..14 kV averaged with its bin weights. Their
pcz is about -1e-4 off on every seed. The hypothesis was that the average
has wider bands than a 20 kV bin. This script

1. ``simulate`` (in the simulators' venv): runs ebsdsim on ``Ni.cif`` with
   the shipped file's settings (20 kV, sample tilt 70 deg, Lambert
   half-width 100, dmin 0.05 nm, rank 8, 1 keV bins, relative_image_stop
   0.01; software Vulkan, k-tile capped at 1000, as
   ``make_master_patterns.py``) and keeps every bin's master pattern,
   weights and energies in ``/tmp/bandwidth/Ni_ebsdsim_bins_hw100.npz``;
2. ``calibrate``: builds master patterns from the bins in the package's
   layout (``avg``: all bins with ebsdsim's weights, as shipped; ``20``,
   ``19`` ...: one bin; ``19-20``: those bins with their weights;
   ``shipped``, ``emsoft``, ``emsoft201``: the package's file, the data's
   own, the data's own on every other grid point, 201 x 201) and calibrates
   each seed's map with each, by the same ``refine_geometry_dic`` call as
   ``bench_uncertainty.py`` (the map's starts kept, only the master
   pattern replaced; ``--reindex``: starts indexed with that master pattern
   instead). Per run: PC errors, standard errors, z, the mean NCC of the
   result, the full field's chi2 and its estimated point spread and
   Kikuchi contrast, and ``clean``: the mean NCC of clean patterns
   projected from that master pattern and the data's at the truth.
   ``--dic-alone`` runs the DIC stage only (``full_field=False``);
   ``--data ebsdsim`` makes the data from the shipped Ni instead (the
   mismatch the other way round); ``--psf``/``--contrast`` force the full
   field's point spread and contrast (a monkeypatch of its estimate);
3. ``profiles``: the mean profile across the (111), (200), (220) and (311)
   bands of each master pattern (over each band's great circle and its
   equivalents): the distance between the flanking dark lines and how much
   wider than the first master pattern's band its profile is (the angular
   stretch that fits best; checked on kinematical Ni: 17 against 20 kV
   reads 1.08 and 1.07 on (220) and (311), lambda's ratio 1.09).

Usage::

    /work/venv-sim/bin/python benchmarks/experiments/bandwidth_bins.py simulate
    python benchmarks/experiments/bandwidth_bins.py calibrate \\
        --masters shipped avg 20 19-20 --seeds 0 1 2 3 4
    python benchmarks/experiments/bandwidth_bins.py calibrate \\
        --masters emsoft avg 20 19 18 17 16 15 14 --seeds 0 1 2 3 4
    python benchmarks/experiments/bandwidth_bins.py calibrate --masters emsoft avg 20 \\
        --seeds 0 1 2 3 4 --psf 0.6 --contrast 0.1
    python benchmarks/experiments/bandwidth_bins.py calibrate --data ebsdsim --reindex \\
        --masters emsoft 20 --seeds 0 1 2 3 4
    python benchmarks/experiments/bandwidth_bins.py profiles \\
        --masters emsoft emsoft201 avg 20 19-20 19 17 14 kin20 kin17 kin23

Log: ``benchmarks/results/uncertainty/bandwidth_bins.log``.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "kikuchipy_geomdic" / "data"
OUT = Path("/tmp/bandwidth")
ENERGY = 20.0
DMIN_NM = 0.05


def simulate(halfw: int, out: Path) -> None:
    """Run ebsdsim on Ni.cif as the shipped Ni_dynamical.npz, keep every bin."""
    import ebsdsim
    import ebsdsim.engine.galerkin_runner as runner

    auto = runner.auto_tile_k

    def capped(*args, **kwargs):
        # lavapipe binds at most 128 MiB per buffer; larger k-tiles fail
        return min(1000, auto(*args, **kwargs))

    runner.auto_tile_k = capped
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    mp = ebsdsim.master_pattern_from_cif(
        str(DATA / "Ni.cif"), voltage_kv=ENERGY, halfw=halfw, dmin=DMIN_NM, sigma_deg=70.0,
        rank=8, energy_binwidth_keV=1.0, relative_image_stop=0.01,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    data, axes = mp.data, mp.axes  # (E, S, H, side, side), raw intensities
    per_bin = data[:, 0][list(axes["bin_to_energy_index"])]  # site-integrated, per bin
    np.savez_compressed(
        out / f"Ni_ebsdsim_bins_hw{halfw}.npz",
        per_bin=per_bin,
        data=data,
        bin_voltages_kv=np.asarray(mp.bin_voltages_kv, dtype=np.float64),
        bin_weights=np.asarray(mp.bin_weights, dtype=np.float64),
        bin_to_energy_index=np.asarray(axes["bin_to_energy_index"]),
        axes=json.dumps({k: repr(v) for k, v in axes.items()}),
        version=ebsdsim.__version__,
        wall_s=wall,
    )
    try:
        mp.save(str(out / f"Ni_ebsdsim_hw{halfw}.h5"))
    except Exception as exc:  # noqa: BLE001 - the npz above is what is used
        print(f"mp.save failed: {exc!r}")
    print(
        f"ebsdsim {ebsdsim.__version__}: data {data.shape}, per_bin {per_bin.shape}, bins "
        f"{mp.bin_voltages_kv} kV, weights {np.round(mp.bin_weights, 4).tolist()}, "
        f"{wall:.0f} s wall",
        flush=True,
    )


# --- master patterns built from the bins (main venv) -------------------------


def _lambert(data: np.ndarray, title: str):
    """An EBSDMasterPattern laid out as the package's ``*_dynamical.npz`` ones."""
    from kikuchipy_geomdic.validation.master_patterns import _lambert_master_pattern, phase

    data = np.asarray(data, dtype=np.float32)
    if data.shape[0] == 1:  # centrosymmetric: ebsdsim stores the north only
        data = np.concatenate([data, data])
    mp = _lambert_master_pattern(data, phase("Ni"))
    mp.metadata.General.title = title
    return mp


def load_bins(path: Path) -> dict:
    npz = np.load(path)
    return dict(
        per_bin=npz["per_bin"].astype(np.float64),
        kv=npz["bin_voltages_kv"],
        w=npz["bin_weights"],
        wall=float(npz["wall_s"]),
    )


def build(bins: dict, which: str) -> tuple[np.ndarray, str]:
    """The master pattern *which*: "avg" (all bins, ebsdsim's weights, as
    shipped), "20" (one bin), "19-20" (bins 19 and 20 kV with their weights),
    "shipped"/"emsoft" (the package's and kikuchipy's) or "emsoft201" (EMsoft's
    on the shipped Ni's 201 x 201 grid) or "kinE" (kinematical at E kV)."""
    from kikuchipy_geomdic.validation import master_patterns

    if which == "shipped":
        return master_patterns.master_pattern("Ni", kind="ebsdsim").data, "shipped Ni_dynamical"
    if which == "emsoft":
        return master_patterns.master_pattern("Ni", kind="emsoft").data, "EMsoft 20 kV (data's)"
    if which == "emsoft201":  # every other grid point of 401 x 401: the shipped Ni's grid
        data = master_patterns.master_pattern("Ni", kind="emsoft").data[:, ::2, ::2]
        return data, "EMsoft 20 kV on 201 x 201 (every other grid point)"
    if which.startswith("kin"):  # kikuchipy's kinematical Ni at that energy (kV)
        e = float(which[3:])
        mp = master_patterns.master_pattern("Ni", kind="kinematical", energy=e)
        return mp.data, f"kinematical {e:g} kV"
    kv, w, per_bin = bins["kv"], bins["w"], bins["per_bin"]
    if which == "avg":
        keep = np.ones(kv.size, bool)
    elif "-" in which:
        lo, hi = (float(v) for v in which.split("-"))
        keep = (kv >= lo - 1e-6) & (kv <= hi + 1e-6)
    else:
        keep = np.isclose(kv, float(which))
    if not keep.any():
        raise ValueError(f"no bin for {which!r}: bins {kv.tolist()} kV")
    data = np.average(per_bin[keep], axis=0, weights=w[keep])
    label = ", ".join(f"{v:g} kV w {x:.4f}" for v, x in zip(kv[keep], w[keep], strict=True))
    return data, f"ebsdsim bins {label}"


# --- calibrations (main venv) -------------------------------------------------

PC = ("pcx", "pcy", "pcz")


def _map(seed: int, calibrate=None, data: str = "emsoft"):
    """Section 1's emsoft-data map of *seed*; with *calibrate*, the same data
    (same truth, noise and uncentred start) but the starts indexed with
    *calibrate* instead of the shipped Ni; with *data* "ebsdsim", the data
    projected from the shipped Ni instead of EMsoft's (section 1's
    ebsdsim-data map when *calibrate* is the shipped Ni)."""
    from bench_realistic import CASES, realistic_map

    from kikuchipy_geomdic.validation import master_patterns, synthetic

    if calibrate is None and data == "emsoft":
        return realistic_map("emsoft-data", seed)
    if calibrate is None:
        return realistic_map("ebsdsim-data", seed)
    return synthetic.synthetic_map(
        calibrate, (11, 11), shape=(96, 96), seed=seed, orientation_error=1.0,
        start="indexed", simulator=master_patterns.master_pattern("Ni", kind=data),
        perturbation=synthetic.DEFAULT_PERTURBATION, camera=CASES["emsoft-data"]["camera"],
    )  # fmt: skip


def _clean_ncc(sm, mp) -> float:
    """Mean NCC of clean patterns projected from *mp* and from the data's
    master pattern at the true geometry and orientations (no camera)."""
    rot = sm.xmap.rotations.reshape(*sm.detector.navigation_shape)
    kw = dict(rotations=rot, detector=sm.detector, energy=sm.energy, compute=True,
              dtype_out=np.float32, show_progressbar=False)  # fmt: skip
    a = sm.simulator.get_patterns(**kw).data.reshape(rot.size, -1).astype(np.float64)
    b = mp.get_patterns(**kw).data.reshape(rot.size, -1).astype(np.float64)
    a = (a - a.mean(1, keepdims=True)) / a.std(1, keepdims=True)
    b = (b - b.mean(1, keepdims=True)) / b.std(1, keepdims=True)
    return float((a * b).mean())


#: The full field's report of an iteration (printed with show_progressbar=True)
FULL_FIELD_LINE = re.compile(
    r"point spread (?P<psf>[-+.\deE]+) px, high-pass (?P<highpass>[-+.\deE]+) px, "
    r"contrast (?P<contrast>[-+.\deE]+)"
)


def calibrate(sm, mp, full_field: bool | None = None) -> dict:
    import contextlib
    import io
    import warnings

    from kikuchipy_geomdic import refine_geometry_dic

    t0 = time.perf_counter()
    out = io.StringIO()
    with (
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(io.StringIO()),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")
        # The progress lines carry the full field's processing model (point spread...)
        res = refine_geometry_dic(
            sm.signal, sm.start_xmap, sm.start_detector, mp, sm.energy,
            points=sm.xmap.size, show_progressbar=True, full_field=full_field,
        )  # fmt: skip
    model = [m.groupdict() for m in FULL_FIELD_LINE.finditer(out.getvalue())]
    # The full field's last chi2 (its noise-weighted residual, same data for every master
    # pattern of a seed)
    chi2 = [h["chi2"] for h in res.history if h.get("stage") == "full-field" and "chi2" in h]
    truth = sm.geometry.as_dict()
    err = {k: float(res.parameters[k] - truth[k]) for k in PC}
    se = {k: float(res.standard_errors[k]) for k in PC}
    return dict(
        err=err, se=se, z={k: err[k] / se[k] for k in PC},
        ncc=float(np.mean(res.xmap.prop["scores"])),
        dic_rms=float(np.mean(res.xmap.prop["dic_rms"])),
        consistent=bool(res.adequacy.get("consistent", True)),
        converged=bool(res.converged), seconds=time.perf_counter() - t0,
        chi2=float(chi2[-1]) if chi2 else float("nan"),
        processing={k: float(v) for k, v in model[-1].items()} if model else {},
    )  # fmt: skip


def _row(name: str, seed: int, r: dict) -> str:
    return (
        f"{name:<8s} seed {seed} | err " + " ".join(f"{r['err'][k]:+.1e}" for k in PC)
        + " | se " + " ".join(f"{r['se'][k]:.1e}" for k in PC)
        + " | z " + " ".join(f"{r['z'][k]:+5.1f}" for k in PC)
        + f" | NCC {r['ncc']:.4f} clean {r['clean_ncc']:.4f} dic_rms {r['dic_rms']:.3f}"
        + f" chi2 {r['chi2']:.6g}"
        + (f" psf {r['processing']['psf']:.2f} c {r['processing']['contrast']:g}"
           if r.get("processing") else "")
        + f"{'' if r['consistent'] else ' inflated'} | {r['seconds']:4.1f} s"
    )  # fmt: skip


def _summary(name: str, rows: list[dict]) -> str:
    e = np.array([[r["err"][k] for k in PC] for r in rows])
    z = np.array([[r["z"][k] for k in PC] for r in rows])
    return (
        f"{name:<8s} n {len(rows)} | mean err " + " ".join(f"{v:+.1e}" for v in e.mean(0))
        + " | RMS z " + " ".join(f"{v:4.2f}" for v in np.sqrt((z**2).mean(0)))
        + f" (all {np.sqrt((z**2).mean()):4.2f}) | mean NCC "
        + f"{np.mean([r['ncc'] for r in rows]):.4f} clean "
        + f"{np.mean([r['clean_ncc'] for r in rows]):.4f}"
    )  # fmt: skip


def force_processing(psf: float | None, contrast: float | None) -> None:
    """Make the full field use this point spread (px) and Kikuchi contrast
    instead of the ones it estimates from the patterns (the rest of its
    estimate kept): the experiment's monkeypatch, not the package's
    behaviour."""
    import dataclasses

    import kikuchipy_geomdic.calibration._full_field as ff

    estimate = ff._estimate_processing

    def forced(*args, **kwargs):
        proc = estimate(*args, **kwargs)
        change = {}
        if psf is not None:
            change["psf"] = psf
        if contrast is not None:
            change["contrast"] = contrast
        return dataclasses.replace(proc, **change)

    ff._estimate_processing = forced


def run_calibrations(bins_path: Path, names: list[str], seeds: list[int], reindex: bool,
                     jsonl: Path | None, dic_alone: bool = False,
                     data_kind: str = "emsoft") -> None:  # fmt: skip
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from kikuchipy_geomdic.validation import master_patterns

    bins = load_bins(bins_path) if bins_path.exists() else None
    if bins is not None:
        print(
            f"bins: {bins['kv'].tolist()} kV, weights {np.round(bins['w'], 4).tolist()}, "
            f"ebsdsim wall {bins['wall'] / 60:.1f} min",
            flush=True,
        )
    mps = {}
    shipped = master_patterns.master_pattern("Ni", kind="ebsdsim").data.astype(np.float64)
    for name in names:
        data, label = build(bins, name)
        mps[name] = _lambert(data, label)
        d = np.asarray(data, dtype=np.float64)
        d = np.concatenate([d, d]) if d.shape[0] == 1 else d
        msg = f"master pattern {name}: {label}"
        if d.shape == shipped.shape:
            c = np.corrcoef(d.ravel(), shipped.ravel())[0, 1]
            rel = np.abs(d - shipped).max() / np.abs(shipped).max()
            msg += f"; vs shipped: r {c:.6f}, max |diff| / max {rel:.1e}"
        print(msg, flush=True)
    rows = {n: [] for n in names}
    for seed in seeds:
        base = _map(seed, data=data_kind)
        for name, mp in mps.items():
            sm = _map(seed, mp, data_kind) if reindex and name != "shipped" else base
            r = calibrate(sm, mp, full_field=False if dic_alone else None)
            r["clean_ncc"] = _clean_ncc(sm, mp)
            r.update(name=name, seed=seed, reindex=reindex, dic_alone=dic_alone, data=data_kind)
            rows[name].append(r)
            print(_row(name, seed, r), flush=True)
            if jsonl is not None:
                with jsonl.open("a") as f:
                    f.write(json.dumps(r) + "\n")
    print("summary (errors over standard errors; mean over seeds)")
    for name in names:
        print(_summary(name, rows[name]), flush=True)


# --- band profiles in the master patterns (main venv) --------------------------

#: Bands whose mean profile across is measured: plane normals (crystal frame)
BANDS = ((1, 1, 1), (2, 0, 0), (2, 2, 0), (3, 1, 1))


def _sample(data: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear intensities of the Lambert master pattern *data* (2, n, n) at
    unit vectors *v* (m, 3), as kikuchipy projects (north for z >= 0)."""
    from kikuchipy.signals.util._master_pattern import _get_lambert_interpolation_parameters

    n = data.shape[-1]
    out = np.empty(len(v))
    for h, sel in ((0, v[:, 2] >= 0), (1, v[:, 2] < 0)):
        if not sel.any():
            continue
        w = v[sel].copy()
        w[:, 2] = np.abs(w[:, 2])
        nii, nij, niip, nijp, di, dj, dim, djm = _get_lambert_interpolation_parameters(
            w, n, n, (n - 1) / 2
        )
        mp = data[h].astype(np.float64)
        out[sel] = (
            mp[nii, nij] * dim * djm + mp[niip, nij] * di * djm
            + mp[nii, nijp] * dim * dj + mp[niip, nijp] * di * dj
        )  # fmt: skip
    return out


def band_profile(data: np.ndarray, hkl, half_deg: float = 6.0, step_deg: float = 0.05):
    """Mean profile across the band of *hkl* (angle from its centre line, deg)
    over its whole great circle and every symmetrically equivalent band, each
    master pattern standardised."""
    import itertools

    data = (data - data.mean()) / data.std()
    t = np.deg2rad(np.arange(-half_deg, half_deg + step_deg / 2, step_deg))
    phi = np.deg2rad(np.arange(0.0, 360.0, 0.25))
    normals = set()
    for perm in itertools.permutations(hkl):
        for signs in itertools.product((1, -1), repeat=3):
            g = np.array(perm) * np.array(signs)
            if tuple(-g) not in normals:
                normals.add(tuple(g))
    prof = np.zeros(t.size)
    for g in normals:
        g = np.asarray(g, float) / np.linalg.norm(g)
        e1 = np.cross(g, [0.3, 0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(g, e1)
        a = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2  # centre line
        v = np.cos(t)[None, :, None] * a[:, None] + np.sin(t)[None, :, None] * g
        prof += _sample(data, v.reshape(-1, 3)).reshape(phi.size, t.size).mean(0)
    return np.rad2deg(t), prof / len(normals)


def _minima(t: np.ndarray, prof: np.ndarray) -> float:
    """Distance (deg) between the two dark lines flanking the band: the minima
    of the symmetrised profile at |t| > 1 deg, each by a parabola through three
    samples."""
    p = 0.5 * (prof + prof[::-1])
    i = int(np.argmin(np.where(t > 1.0, p, np.inf)))
    y0, y1, y2 = p[i - 1], p[i], p[i + 1]
    return 2 * (t[i] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) * (t[1] - t[0]))


def _scale(t: np.ndarray, ref: np.ndarray, prof: np.ndarray, within: float = 3.5) -> float:
    """How much wider *prof*'s band is than *ref*'s: 1 / s for the stretch s of the
    angle with which a * prof(t / s) + b fits ref(t) best (least squares over
    |t| < *within* deg, s on a 0.0005 grid in 0.8-1.25); > 1: *prof* wider."""
    ref = 0.5 * (ref + ref[::-1])
    prof = 0.5 * (prof + prof[::-1])
    sel = np.abs(t) < within
    best = (np.inf, 1.0)
    for sc in np.arange(0.8, 1.25 + 1e-9, 0.0005):
        q = np.interp(t[sel] / sc, t, prof)
        a = np.vstack([q, np.ones_like(q)]).T
        res = np.linalg.lstsq(a, ref[sel], rcond=None)[1]
        best = min(best, (float(res[0]) if res.size else 0.0, sc))
    return 1 / best[1]


def run_profiles(bins_path: Path, names: list[str]) -> None:
    bins = load_bins(bins_path) if bins_path.exists() else None
    ref, rows = None, []
    for name in names:
        data, _ = build(bins, name)
        data = np.asarray(data, dtype=np.float64)
        data = np.concatenate([data, data]) if data.shape[0] == 1 else data
        profs = [band_profile(data, hkl, half_deg=5.0, step_deg=0.02) for hkl in BANDS]
        ref = profs if ref is None else ref
        rows.append((name, [_minima(*p) for p in profs],
                     [_scale(p[0], r[1], p[1]) for p, r in zip(profs, ref)]))  # fmt: skip
    print(
        "band profiles (mean across each band over its great circle and equivalents): "
        f"distance between the flanking dark lines (deg); x how much wider than "
        f"{names[0]}'s band by the stretch that fits its profile best"
    )
    print(f"{'master':<10s} " + " ".join(f"{str(b):>16s}" for b in BANDS))
    for name, mins, scales in rows:
        print(
            f"{name:<10s} " + " ".join(f"{m:7.3f} x{sc:7.4f}" for m, sc in zip(mins, scales)),
            flush=True,
        )
    # Bragg's law at 20 kV for reference: 2 theta_B of each band (relativistic lambda)
    a = 3.524
    e = 20e3
    wl = 12.2643 / np.sqrt(e * (1 + 0.97848e-6 * e))  # angstrom
    print(
        f"{'2 theta_B':<10s} "
        + " ".join(
            f"{2 * np.rad2deg(np.arcsin(wl * np.linalg.norm(b) / (2 * a))):10.3f}" for b in BANDS
        )
        + "  (kinematical, 20 kV, a = 3.524 angstrom)"
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("simulate")
    s.add_argument("--halfw", type=int, default=100)
    s.add_argument("--out", type=Path, default=OUT)
    c = sub.add_parser("calibrate")
    c.add_argument("--bins", type=Path, default=OUT / "Ni_ebsdsim_bins_hw100.npz")
    c.add_argument("--masters", nargs="+", default=["shipped", "avg", "20", "19-20"])
    c.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    c.add_argument("--reindex", action="store_true")
    c.add_argument("--json", type=Path, default=None)
    c.add_argument("--dic-alone", action="store_true", help="full_field=False")
    c.add_argument("--psf", type=float, default=None, help="force the full field's psf")
    c.add_argument("--contrast", type=float, default=None, help="... and contrast")
    c.add_argument("--data", choices=["emsoft", "ebsdsim"], default="emsoft",
                   help="the data's master pattern (ebsdsim: the shipped Ni)")  # fmt: skip
    pr = sub.add_parser("profiles")
    pr.add_argument("--bins", type=Path, default=OUT / "Ni_ebsdsim_bins_hw100.npz")
    pr.add_argument("--masters", nargs="+", default=["emsoft", "avg", "20", "17", "14"])
    args = ap.parse_args(argv)
    if args.cmd == "simulate":
        simulate(args.halfw, args.out)
    elif args.cmd == "profiles":
        run_profiles(args.bins, args.masters)
    else:
        import subprocess

        commit = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
            text=True,
        ).stdout.strip()  # fmt: skip
        print(f"command: experiments/bandwidth_bins.py {' '.join(argv)}  (code {commit})")
        if args.psf is not None or args.contrast is not None:
            force_processing(args.psf, args.contrast)
        run_calibrations(
            args.bins, args.masters, args.seeds, args.reindex, args.json, args.dic_alone,
            args.data,
        )  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])

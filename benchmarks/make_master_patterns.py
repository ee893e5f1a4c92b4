"""Compute the iron phases' master patterns shipped in ``kikuchipy_geomdic/data``.

Not part of the package: run it in a separate environment with the
simulators (``pip install ebsdsim==0.2.4 de-ebsd==0.2.1``), one phase and
simulator per call, as the shipped Ni and BaTiO3 files were made (see
``kikuchipy_geomdic/data/README.md``)::

    python benchmarks/make_master_patterns.py ebsdsim Fe_bcc --out /tmp/mp
    python benchmarks/make_master_patterns.py de-ebsd Fe_bcc --out /tmp/mp --halfw 100

- ``ebsdsim``: ``master_pattern_from_cif`` at 20 kV, sample tilt 70 deg,
  Lambert half-width 100, dmin 0.05 nm, Galerkin rank 8, 1 keV energy bins
  (ebsdsim stops adding bins by itself, ``relative_image_stop`` 0.01); the
  per-bin master patterns averaged with ebsdsim's bin weights (float64,
  stored float32), as kikuchipy's ebsdsim reader lays them out (the
  site-integrated slice; a centrosymmetric phase's north hemisphere
  repeated as the south). On a CPU it needs Mesa's software Vulkan
  (lavapipe), whose 128 MiB buffer limit the k-tile cap of 1000 respects.
- ``de-ebsd``: ``MasterPatternSimulator`` with its default Bloch-wave
  backend and its own Monte Carlo depth profile, 20 kV, sample tilt 70 deg,
  dmin 0.05 nm, on CPU with torch's threads set by ``--threads``.

Each writes ``{phase}_{ebsdsim|deebsd}_hw{halfw}.npz`` with the package's
keys: ``data`` (2, n, n) float32 north then south, ``cif`` (the CIF's
text), ``energy`` (20.0) and ``source`` (how it was made, with the wall
time). ``--ship FILE NAME`` copies such a file into the package data as
``NAME``, with ``--float16`` rounding the intensities (as BaTiO3's de-ebsd
pattern is stored) and saying so in ``source``::

    python benchmarks/make_master_patterns.py --ship /tmp/mp/Fe_bcc_deebsd_hw200.npz \
        Fe_bcc_deebsd.npz --float16
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "kikuchipy_geomdic" / "data"
ENERGY = 20.0
DMIN_NM = 0.05


def _ebsdsim(cif: Path, halfw: int) -> tuple[np.ndarray, str]:
    import ebsdsim
    import ebsdsim.engine.galerkin_runner as runner

    auto = runner.auto_tile_k

    def capped(*args, **kwargs):
        # lavapipe binds at most 128 MiB per buffer; larger k-tiles fail
        return min(1000, auto(*args, **kwargs))

    runner.auto_tile_k = capped
    mp = ebsdsim.master_pattern_from_cif(
        str(cif), voltage_kv=ENERGY, halfw=halfw, dmin=DMIN_NM, sigma_deg=70.0, rank=8,
        energy_binwidth_keV=1.0, relative_image_stop=0.01,
    )  # fmt: skip
    data, axes = mp.data, mp.axes  # (E, S, H, side, side), raw intensities
    per_bin = data[:, 0][list(axes["bin_to_energy_index"])]  # site-integrated
    weights = np.asarray(mp.bin_weights, dtype=np.float64)
    mean = np.average(per_bin.astype(np.float64), axis=0, weights=weights)
    if mean.shape[0] == 1:  # centrosymmetric: ebsdsim stores the north only
        mean = np.concatenate([mean, mean])
    bins = ", ".join(
        f"{v:g} kV w {w:.4f}" for v, w in zip(mp.bin_voltages_kv, mp.bin_weights, strict=True)
    )
    settings = (
        f"ebsdsim {ebsdsim.__version__} (MIT), master_pattern_from_cif, 20 kV, sample tilt "
        f"(sigma) 70 deg, Lambert half-width {halfw} ({2 * halfw + 1} x {2 * halfw + 1}), dmin "
        f"{DMIN_NM} nm, Bloch waves, Galerkin rank 8, Bethe 20/40/200, surrogate Monte Carlo "
        f"energy model, 1 keV energy bins, relative_image_stop 0.01, {len(weights)} bins run "
        f"({bins}); per-bin master patterns (site-integrated) averaged with ebsdsim's bin "
        "weights (np.average, float64, stored float32); data[0] north, data[1] south; "
        "software Vulkan (lavapipe), k-tile capped at 1000"
    )
    return mean.astype(np.float32), settings


def _deebsd(cif: Path, halfw: int, threads: int) -> tuple[np.ndarray, str]:
    import de_ebsd as de
    import torch

    torch.set_num_threads(threads)
    crystal = de.Crystal.from_cif(str(cif))
    microscope = de.Microscope(energy=ENERGY * 1e3, sample_tilt=70.0)
    sim = de.MasterPatternSimulator(crystal, microscope, npx=halfw, dmin=DMIN_NM)
    master = sim.compute(device="cpu")
    data = master.data[0].detach().cpu().numpy().astype(np.float32)  # (2, n, n), north first
    settings = (
        f"de-ebsd {de.__version__} (GPL-3.0-or-later), MasterPatternSimulator, Bloch-wave "
        f"backend bloch_prism, Lambert half-width {halfw} ({2 * halfw + 1} x {2 * halfw + 1}), "
        f"dmin {DMIN_NM} nm, 20 kV, sample tilt 70 deg, native Monte Carlo depth profile "
        f"(200 000 electrons), single energy map; CPU, {threads} torch thread(s)"
    )
    return data, settings


def ship(path: Path, name: str, float16: bool) -> None:
    """Copy a computed master pattern into the package data."""
    npz = dict(np.load(path))
    data = npz["data"]
    source = str(npz["source"])
    if float16:
        rel = np.abs(data.astype(np.float16).astype(np.float64) / data - 1)
        data = data.astype(np.float16)
        source += f"; intensities stored as float16 (relative rounding <= {rel.max():.1e})"
    npz.update(data=data, source=source)
    np.savez_compressed(DATA / name, **npz)
    print(f"{DATA / name}: {data.shape} {data.dtype}, {(DATA / name).stat().st_size} bytes")


def main(argv=None) -> None:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "--ship":
        ship(Path(argv[1]), argv[2], "--float16" in argv)
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("simulator", choices=["ebsdsim", "de-ebsd"])
    p.add_argument("phase", help="CIF stem in kikuchipy_geomdic/data, e.g. Fe_bcc")
    p.add_argument("--halfw", type=int, default=100, help="Lambert half-width")
    p.add_argument("--threads", type=int, default=1, help="torch threads (de-ebsd)")
    p.add_argument("--out", type=Path, default=Path("."))
    args = p.parse_args(argv)
    cif = DATA / f"{args.phase}.cif"
    t0 = time.perf_counter()
    if args.simulator == "ebsdsim":
        data, settings = _ebsdsim(cif, args.halfw)
    else:
        data, settings = _deebsd(cif, args.halfw, args.threads)
    minutes = (time.perf_counter() - t0) / 60
    source = f"{settings}; CIF {cif.name}; {minutes:.1f} min wall on 2 shared cores"
    args.out.mkdir(parents=True, exist_ok=True)
    tag = "ebsdsim" if args.simulator == "ebsdsim" else "deebsd"
    out = args.out / f"{args.phase}_{tag}_hw{args.halfw}.npz"
    np.savez_compressed(out, data=data, cif=cif.read_text(), energy=ENERGY, source=source)
    print(f"{out}: {data.shape} {data.dtype}, {minutes:.1f} min\n{source}", flush=True)


if __name__ == "__main__":
    main()

"""The benchmarks page's summary figure, drawn from logs already in
``results/`` (no calibration runs; a few seconds).

Usage::

    python benchmarks/plot_summary.py            # writes results/summary.png

Panels, every number read from a file:

(a) the PC error at the map centre on the realistic Ni maps, per case:
    the default calibration and the DIC stage alone (every seed), and
    kikuchipy's Nelder-Mead with the PCs averaged (seed 0, where it ran):
    ``results/realistic/bench_realistic.log``,
    ``bench_realistic_mismatch_seeds345.log``, ``bench_realistic_kikuchipy.log``;
(b) does the error bar cover? The largest |error| / standard error of
    pcx, pcy, pcz per map, from the same logs, and the BaTiO3 domain maps
    of ``bench_crystal.py`` with the free and the crystal orientation
    model (``results/crystal/bench_crystal_*.log``);
(c) the PC error against dose on a BaTiO3 stripe-domain map
    (``results/variants_picks.log``, dose 0.3 from
    ``variants_picks_dose03.log``), with kikuchipy's Nelder-Mead and
    differential-evolution detectors at dose 100
    (``results/variants_detectors.log``).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import matplotlib.pyplot as plt

RESULTS = Path(__file__).resolve().parent / "results"
REALISTIC = ("bench_realistic.log", "bench_realistic_mismatch_seeds345.log")
CASES = ("moderate", "real-noise", "emsoft-data", "ebsdsim-data", "far", "model-family")
LABELS = {
    "moderate": "moderate\n150/px",
    "real-noise": "real-Ni\nnoise 30/px",
    "emsoft-data": "EMsoft data\nebsdsim MP",
    "ebsdsim-data": "ebsdsim data\nEMsoft MP",
    "far": "start\n4 % off",
    "model-family": "model\nfamily",
}
ROW = re.compile(
    r"^(?P<case>[\w-]+)\s+(?P<seed>\d+)\s+(?P<method>default|DIC alone|kikuchipy NM)\s+"
    r"(?P<time>[\d.]+)\s+(?P<pc>[\d.e+-]+)\s+(?P<field>[\d.e+-]+)"
    r"(?:\s+(?P<z>[-+\d.]+,[-+\d.]+,[-+\d.]+))?"
)
CRYSTAL = re.compile(
    r"^(?P<case>\w+)\s+seed (?P<seed>\d+) (?P<model>crystal|free)\s+\|.*max z\s+(?P<z>[\d.]+)"
)
PICKS = re.compile(r"^\s+(?P<dose>[\d.]+)\s+(?P<pc>\d\.\d+e[-+]\d+)\s+[-+]")
DETECTOR = re.compile(r"^kikuchipy (?P<method>NM|DE) avg\s+\d+\s+\d+\s+(?P<pc>[\d.e+-]+)")


def realistic_rows() -> list[dict]:
    """Rows of the realistic benchmark's logs: case, seed, method, PC error, largest |z|."""
    rows = []
    for name in (*REALISTIC, "bench_realistic_kikuchipy.log"):
        for line in (RESULTS / "realistic" / name).read_text().splitlines():
            m = ROW.match(line)
            if m is None:
                continue
            if name.endswith("kikuchipy.log") and m["method"] != "kikuchipy NM":
                continue  # the same maps' default rows are in bench_realistic.log
            z = m["z"]
            rows.append(
                dict(
                    case=m["case"],
                    seed=int(m["seed"]),
                    method=m["method"],
                    pc=float(m["pc"]),
                    z=max(abs(float(v)) for v in z.split(",")) if z else None,
                )
            )
    return rows


def crystal_rows() -> list[dict]:
    rows = []
    for path in sorted((RESULTS / "crystal").glob("bench_crystal_*.log")):
        for line in path.read_text().splitlines():
            m = CRYSTAL.match(line)
            if m and float(m["z"]) > 0:  # 0: infinite standard errors, said so
                rows.append(
                    dict(case=m["case"], seed=int(m["seed"]), model=m["model"], z=float(m["z"]))
                )
    return rows


ENVELOPE = re.compile(
    r"^(?P<kind>poly|single|domains)\s+\S+\s+seed \d+ (?P<model>\S+)\s+\| PC err .*\| se "
    r"(?P<se>\S+) .*max z\s+(?P<z>[\d.]+)"
)


def envelope_rows() -> list[dict]:
    """Section 8's envelope: largest error / se per map (finite ones), the
    current code's (logs of earlier code are named ``*before*``)."""
    rows = []
    for path in sorted((RESULTS / "envelope").glob("bench_envelope_*.log")):
        if "before" in path.name:
            continue
        for line in path.read_text().splitlines():
            m = ENVELOPE.match(line)
            if m and m["se"] != "inf":
                rows.append(dict(kind=m["kind"], model=m["model"], z=float(m["z"])))
    return rows


def picks() -> dict[float, float]:
    """Largest PC error on the map against dose; dose 0.3 from its rerun."""
    out = {}
    for name in ("variants_picks.log", "variants_picks_dose03.log"):
        for line in (RESULTS / name).read_text().splitlines():
            m = PICKS.match(line)
            if m:
                out[float(m["dose"])] = float(m["pc"])
    return dict(sorted(out.items()))


def detectors() -> dict[str, float]:
    out = {}
    for line in (RESULTS / "variants_detectors.log").read_text().splitlines():
        m = DETECTOR.match(line)
        if m:
            out[m["method"]] = float(m["pc"])
    return out


def jitter(i: int, k: int, width: float = 0.08) -> float:
    return (i - (k - 1) / 2) * width


def columns(ax, groups, key: str, offset: float, width: float, **style) -> None:
    """Plot ``row[key]`` of each group of rows in its own column (the
    group's index), shifted by *offset* and spread by *width*."""
    xs, ys = [], []
    for c, sel in enumerate(groups):
        for i, r in enumerate(sel):
            xs.append(c + offset + jitter(i, len(sel), width))
            ys.append(r[key])
    ax.plot(xs, ys, ls="none", **style)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=RESULTS / "summary.png")
    args = p.parse_args()

    plt.switch_backend("agg")
    rows, crystal = realistic_rows(), crystal_rows()
    fig, axes = plt.subplots(1, 3, figsize=(18.5, 4.8), width_ratios=(1.25, 2.0, 1))
    styles = {
        "default": dict(color="tab:blue", marker="o", label="this package, default"),
        "DIC alone": dict(color="tab:orange", marker="s", label="DIC stage alone"),
        "kikuchipy NM": dict(color="tab:red", marker="*", ms=11, label="kikuchipy NM (seed 0)"),
    }
    offsets = {"default": -0.2, "DIC alone": 0.0, "kikuchipy NM": 0.2}

    ax = axes[0]
    for method, style in styles.items():
        cases = [[r for r in rows if r["case"] == c and r["method"] == method] for c in CASES]
        columns(ax, cases, "pc", offsets[method], 0.03, alpha=0.85, **style)
    ax.set_yscale("log")
    ax.set_xticks(range(len(CASES)), [LABELS[c] for c in CASES], fontsize=7)
    ax.set_ylabel("largest PC error at the map centre")
    ax.set_title("(a) realistic Ni maps, 121 points of 96 px", fontsize=10)
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(axis="y", alpha=0.3)

    ax = axes[1]
    for method in ("default", "DIC alone"):
        cases = [[r for r in rows if r["case"] == c and r["method"] == method] for c in CASES]
        columns(ax, cases, "z", offsets[method], 0.03, alpha=0.85, **styles[method])
    envelope = envelope_rows()
    kinds = ("poly", "single", "domains")
    models = (("free", -0.15, "tab:blue", "free model"), ("crystal", 0.15, "tab:green", "crystal"))
    for model, offset, color, _ in models:
        lead = [[]] * len(CASES) + [[r for r in crystal if r["model"] == model]]
        label = f"single crystals, {'free model' if model == 'free' else 'crystal model'}"
        columns(ax, lead, "z", offset, 0.05, color=color, marker="D", label=label)
    for model, offset, color, name in models:
        groups = [[]] * (len(CASES) + 1) + [
            [r for r in envelope if r["kind"] == k and r["model"] == model] for k in kinds
        ]
        columns(ax, groups, "z", offset, 0.05, color=color, marker="^", mfc="none",
                label=f"envelope, {name}")  # fmt: skip
    for level, ls in ((1, ":"), (3, "--")):
        ax.axhline(level, color="gray", ls=ls, lw=1)
    ax.set_yscale("log")
    ax.set_xticks(
        range(len(CASES) + 1 + len(kinds)),
        [*(LABELS[c] for c in CASES), "single\ncrystals", *(f"envelope\n{k}" for k in kinds)],
        fontsize=7,
    )
    ax.set_ylabel("largest |error| / standard error (pcx, pcy, pcz)")
    ax.set_title("(b) does the error bar cover? (dashed: 3)", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(axis="y", alpha=0.3)

    ax = axes[2]
    curve = picks()
    ax.plot(
        list(curve), list(curve.values()), "o-", color="tab:blue", label="this package, default"
    )
    det = detectors()
    for method, marker, color in (("NM", "*", "tab:red"), ("DE", "^", "tab:purple")):
        if method in det:
            ax.plot(
                [100],
                [det[method]],
                marker,
                color=color,
                ms=10,
                label=f"kikuchipy {method}, PCs averaged",
            )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("dose (counts per pixel)")
    ax.set_ylabel("largest PC error on the map")
    ax.set_title("(c) BaTiO3 stripe domains, start 3 % off", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)

    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

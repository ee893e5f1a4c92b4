"""README.md says what is true: its commands, the demo's output, the "Use"
block and the result it prints, its links.

- The first code block holds the two set-up commands; ``.ci/run`` runs its
  line with ``pytest`` verbatim.
- The demo's output block has the form the demo prints, and its table adds
  up (error = refined - true).
- The "Use" block runs as written on a map read from files: a small
  synthetic silicon map (3 x 3 patterns of 40 x 40 px, a known geometry,
  starting orientations 0.3 deg off) written as a kikuchipy h5ebsd file, its
  starting orientations as an ``.ang`` file (orix) and the shipped silicon
  master pattern in EMsoft's format, under the names the README uses. What
  ``print(result)`` shows there is the README's result block.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import kikuchipy as kp
import matplotlib.pyplot as plt
import numpy as np
import pytest
from cli.test_cli import write_emsoft_master_pattern
from orix import io as orix_io

from kikuchipy_geomdic.validation import synthetic

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
FILES = ("map.h5", "map.ang", "Si-master-20kV.h5")
COMMANDS = [
    "python -m pip install . && kikuchipy-geomdic demo",
    'python -m pip install ".[tests]" && python -m pytest -n 2',
]
ROWS = ("pcx", "pcy", "pcz", "tilt", "azimuthal", "sample_tilt", "tilt-sample_tilt")


def text() -> str:
    return README.read_text(encoding="utf-8")


def blocks(section: str = "") -> list[tuple[str, str]]:
    """(language, body) of each fenced block, from *section*'s heading on."""
    t = text()
    t = t[t.index(f"\n{section}\n") :] if section else t
    return re.findall(r"^```(\w*)\n(.*?)^```", t, flags=re.S | re.M)


def use_block() -> str:
    """The first python code block after the "## Use" heading."""
    code = [body for lang, body in blocks("## Use") if lang == "python"]
    assert code, "README.md's Use section has no python block"
    return code[0]


def result_block() -> list[str]:
    """The text block after the Use block: what print(result) shows."""
    after = blocks("## Use")
    i = next(i for i, (lang, _) in enumerate(after) if lang == "python")
    lang, body = after[i + 1]
    assert lang == "text"
    return body.splitlines()


def is_row(cols: list[str]) -> bool:
    """Whether a line's columns are a row of a GeometryRefinementResult table."""
    return len(cols) > 3 and cols[0] in ROWS and re.fullmatch(r"[-+]?[\d.]+", cols[1]) is not None


def table(lines: list[str]) -> dict[str, list[str]]:
    """Rows of a GeometryRefinementResult table: name -> its columns."""
    return {c[0]: c[1:] for c in map(str.split, lines) if is_row(c)}


def without_sigma(line: str) -> str:
    """A line of print(result), the standard error of a table row left out."""
    cols = line.split()
    if is_row(cols):
        del cols[3]  # name, start, refined, sigma, ...
    return " ".join(cols)


def test_first_block_holds_the_two_commands():
    lang, body = blocks()[0]
    assert lang == "bash"
    assert body.splitlines() == COMMANDS
    # What .ci/run executes: the first line of that block with pytest
    assert [ln for ln in body.splitlines() if "pytest" in ln][0] == COMMANDS[1]


def test_demo_output_has_the_demo_form():
    lang, body = blocks()[1]
    assert lang == "text"
    lines = body.splitlines()
    assert lines[0].startswith("Synthetic silicon map: 10 x 10 patterns of 120 x 120 px")
    assert lines[-1] == "Figures written to geomdic-demo/"
    header = r"GeometryRefinementResult \(joint solver, 100 points"
    assert any(re.match(header, ln) for ln in lines)
    columns = "parameter start refined sigma true error unit"
    assert columns in [" ".join(ln.split()) for ln in lines]
    rows = table(lines)
    assert set(rows) == set(ROWS)
    for name, (_, refined, _, true, error, *_) in rows.items():
        assert float(error) == pytest.approx(float(refined) - float(true), abs=2e-6), name


def test_readme_is_short_and_its_links_resolve():
    lines = text().splitlines()
    assert len(lines) <= 120
    targets = re.findall(r"\]\(([^)]+)\)", text())
    local = [t.split("#")[0] for t in targets if not t.startswith(("http://", "https://"))]
    assert local, "README.md links to no page of the book"
    for target in local:
        assert (ROOT / target).exists(), target


def test_use_block_names_the_files():
    code = use_block()
    for name in FILES:
        assert f'"{name}"' in code


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("readme")
    sm = synthetic.synthetic_map("Si", (3, 3), shape=(40, 40), seed=0)
    sm.signal.save(d / "map.h5")
    with contextlib.redirect_stdout(io.StringIO()):  # orix prints about phase names
        orix_io.save(str(d / "map.ang"), sm.start_xmap)
    write_emsoft_master_pattern(sm.master_pattern, d / "Si-master-20kV.h5")
    return d, sm


def test_kikuchipy_alone_refuses_the_file_read_map(files):
    """Why the README reindexes with this package's reindex."""
    d, sm = files
    with contextlib.redirect_stdout(io.StringIO()):
        xmap = orix_io.load(str(d / "map.ang"))
    mp = kp.load(d / "Si-master-20kV.h5", projection="lambert", hemisphere="both", energy=20)
    assert xmap.phases[int(xmap.phase_id[0])].point_group.name == "432"
    assert mp.phase.point_group.name == "m-3m"
    s = kp.load(d / "map.h5")
    with pytest.raises(ValueError, match="must be the same"):
        with contextlib.redirect_stdout(io.StringIO()):
            s.refine_orientation(xmap, s.detector, mp, 20)


def test_use_block_runs_as_written(files, monkeypatch):
    d, sm = files
    monkeypatch.chdir(d)
    namespace = {"__name__": "readme_use"}
    stdout = io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout):
            exec(compile(use_block(), str(README), "exec"), namespace)
    finally:
        plt.close("all")

    result, xmap_all = namespace["result"], namespace["xmap_all"]
    true, start = sm.geometry.as_dict(), sm.start_geometry.as_dict()
    for k in ("pcx", "pcy", "pcz"):
        assert abs(start[k] - true[k]) > 5e-3  # the start is off: the test can fail
        assert abs(result.parameters[k] - true[k]) < 1e-3, (k, result.parameters[k], true[k])
    assert result.detector.navigation_shape == (3, 3)
    assert xmap_all.shape == (3, 3)
    assert xmap_all.refined.all() and xmap_all.scores.min() > 0.99
    # A 3 x 3 map does not determine the detector tilt (kept at its start,
    # 0.9 deg off): the orientations share that rotation and are otherwise right
    diff = ~sm.xmap.rotations * xmap_all.rotations
    assert np.rad2deg((diff * ~diff[0]).angle).max() < 0.05
    with contextlib.redirect_stdout(io.StringIO()):
        back = orix_io.load(str(d / "map_refined.ang"))
    assert back.shape == (3, 3)

    # The README's result block is what print(result) printed, but for the
    # standard errors of this noise-free map (numerical noise, ~1e-10)
    shown = result_block()
    printed = str(result).splitlines()[: len(shown)]
    assert [without_sigma(ln) for ln in shown] == [without_sigma(ln) for ln in printed]
    assert printed[0] in stdout.getvalue()


def test_benchmarks_page_and_changelog_are_a_readers_size():
    """The benchmarks page answers a user's questions in a minute; the
    changelog's newest section says what changed, not how."""
    assert len((ROOT / "benchmarks" / "README.md").read_text().splitlines()) <= 400
    lines = (ROOT / "CHANGELOG.md").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("## ["))
    later = [i for i in range(first + 1, len(lines)) if lines[i].startswith("## [")]
    end = later[0] if later else len(lines)
    assert end - first <= 120

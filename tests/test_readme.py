"""README.md's "Use" block runs as written on a map read from files.

A small synthetic silicon map (3 x 3 patterns of 40 x 40 px, a known
geometry, starting orientations 0.3 deg off) is written as a kikuchipy
h5ebsd file, its starting orientations as an ``.ang`` file (orix) and the
shipped silicon master pattern in EMsoft's format, under the names the
README uses. The README's code is then executed unchanged in that folder.
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
from orix import io as orix_io
from test_cli import write_emsoft_master_pattern

from kikuchipy_geomdic.validation import synthetic

README = Path(__file__).resolve().parents[1] / "README.md"
FILES = ("map.h5", "map.ang", "Si-master-20kV.h5")


def use_block() -> str:
    """The first python code block after the "## Use" heading."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("\n## Use\n") :]
    match = re.search(r"```python\n(.*?)```", section, flags=re.S)
    assert match, "README.md's Use section has no python block"
    return match.group(1)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("readme")
    sm = synthetic.synthetic_map("Si", (3, 3), shape=(40, 40), seed=0)
    sm.signal.save(d / "map.h5")
    with contextlib.redirect_stdout(io.StringIO()):  # orix prints about phase names
        orix_io.save(str(d / "map.ang"), sm.start_xmap)
    write_emsoft_master_pattern(sm.master_pattern, d / "Si-master-20kV.h5")
    return d, sm


def test_use_block_names_the_files():
    code = use_block()
    for name in FILES:
        assert f'"{name}"' in code


def test_kikuchipy_alone_refuses_the_file_read_map(files):
    """Why the README reindexes with kikuchipy_geomdic.indexing.reindex.reindex."""
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
    assert "pcx" in stdout.getvalue()  # print(result)
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

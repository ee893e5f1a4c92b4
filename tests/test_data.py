"""The real data the tutorials read: kikuchipy's silicon moving-screen
patterns (H. W. Anes, J. Hjelen, NTNU, kikuchipy-data, CC BY 4.0).

They are third-party data and not in this repository: they are read offline
from the kikuchipy data cache that ``KIKUCHIPY_DATA_DIR`` names (conftest
points it at ``../shared/data/kikuchipy_cache`` when that exists). Without
them these tests skip, saying how to get them; they fail when the run asks
for the data (``KIKUCHIPY_DATA_DIR`` set before pytest starts, as
``.ci/run`` sets it, or ``--require-data``).
"""

import conftest
import kikuchipy as kp
import numpy as np
import pytest
from conftest import _si_moving_screen, data_required

NAMES = {0: "si_in", 5: "si_out5mm", 10: "si_out10mm"}


@pytest.mark.parametrize("distance", NAMES)
def test_si_moving_screen_pattern(si_moving_screen, distance):
    """What tutorial 02a relies on: one 480 x 480 pattern at 20 kV and 70 deg
    sample tilt with its static background, the file of that camera move."""
    s = si_moving_screen(distance)
    assert s.metadata.General.title.startswith(NAMES[distance])
    assert s.axes_manager.navigation_shape == ()
    assert s.data.shape == (480, 480) and s.data.dtype == np.uint8
    assert s.static_background.shape == (480, 480)
    assert s.metadata.Acquisition_instrument.SEM.beam_energy == 20
    assert s.detector.sample_tilt == 70
    # A pattern, not a blank frame: its intensities span much of the range
    assert s.data.max() - s.data.min() > 100
    # The tutorial's processing leaves finite, non-constant intensities
    s.remove_static_background("divide", show_progressbar=False)
    s.remove_dynamic_background("divide", show_progressbar=False)
    assert np.isfinite(s.data).all() and s.data.std() > 0


def test_si_moving_screen_patterns_differ(si_moving_screen):
    """The camera moved between the three: no two patterns are the same."""
    data = [si_moving_screen(d).data.astype(np.float64) for d in NAMES]
    for i in range(3):
        for j in range(i + 1, 3):
            assert np.abs(data[i] - data[j]).mean() > 1


def _not_in_cache(distance, allow_download=False, **kwargs):
    raise ValueError("File data/silicon_ebsd_moving_screen/si_in.h5 must be downloaded")


@pytest.mark.parametrize("required", [True, False])
def test_missing_data_names_the_variable(monkeypatch, required):
    """Not found offline: the test fails where the data are required and
    skips where not, saying what to set either way."""
    monkeypatch.setattr(kp.data, "si_ebsd_moving_screen", _not_in_cache)
    outcome = pytest.fail.Exception if required else pytest.skip.Exception
    with pytest.raises(outcome, match="KIKUCHIPY_DATA_DIR") as info:
        _si_moving_screen(0, required)
    assert "must be downloaded" in str(info.value)
    assert "allow_download=True" in str(info.value)


def test_data_required_by_option(pytestconfig, monkeypatch):
    """``--require-data`` asks for the data whatever the environment."""
    monkeypatch.setattr(conftest, "_DATA_ASKED", False)
    monkeypatch.setattr(pytestconfig.option, "require_data", True)
    assert data_required(pytestconfig)
    monkeypatch.setattr(pytestconfig.option, "require_data", False)
    assert not data_required(pytestconfig)

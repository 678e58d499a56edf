"""The grasp's stabilised P1-P1 u-p element does not lock: Cook's membrane (neo-Hookean,
nu = 0.499) with beta = 0.2 is within 1 % of the converged Taylor-Hood deflection (8.11 mm,
tests/test_locking.py) at n = 8, where plain P1 (= p1-p0 on tets) gives 2.77 mm."""

import importlib.util

import pytest

from handfe.grasp.fe import STAB_BETA
from handfe.paths import REPO_ROOT


def _cook():
    spec = importlib.util.spec_from_file_location(
        "p1p1s_cook", REPO_ROOT / "benchmarks" / "p1p1s_cook_membrane.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.cook


def test_stabilised_p1p1_is_locking_free():
    cook = _cook()
    d4, d8 = cook(4, STAB_BETA), cook(8, STAB_BETA)
    assert d8 == pytest.approx(8.11, rel=0.01)
    assert d4 < d8  # converges from below, like Taylor-Hood
    # without the stabilisation equal-order P1-P1 is far off (5.5 mm)
    assert abs(cook(8, 0.0) - 8.11) > 10 * abs(d8 - 8.11)

"""`handfe material`: the issue's acceptance command and error handling."""

import io
from contextlib import redirect_stderr, redirect_stdout

import numpy as np
import pytest

from handfe.cli import main
from handfe.materials import Ogden


def run(argv):
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse errors
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def test_ogden_skin_uniaxial_incompressible_acceptance():
    code, out, _ = run(["material", "ogden", "--preset", "skin", "--mode", "uniaxial",
                        "--stretch", "0.6:1.6:11", "--incompressible"])
    assert code == 0
    lines = out.strip().splitlines()
    assert lines[0] == "stretch,nominal_stress_MPa,tangent_MPa,stable,fe_nominal_stress_MPa"
    data = np.array([[float(x) for x in ln.split(",")] for ln in lines[1:]])
    assert data.shape == (11, 5)
    m = Ogden.skin()
    lam = data[:, 0]
    ref = sum(2 * mu / a * (lam ** (a - 1) - lam ** (-a / 2 - 1))
              for mu, a in zip(m.mu_MPa, m.alpha, strict=True))
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(data[:, 1], ref, rtol=1e-6, atol=1e-12 * scale)
    np.testing.assert_allclose(data[:, 4], ref, rtol=1e-4, atol=1e-10 * scale)
    assert np.all(data[:, 3] == 1)  # stable over 0.6..1.6


@pytest.mark.parametrize("argv,needle", [
    (["material", "ogden", "--preset", "bogus", "--no-fe"], "unknown ogden preset 'bogus'"),
    (["material", "ogden", "--preset", "skin", "--stretch=-0.5:1.2:3", "--no-fe"],
     "must be positive"),
    (["material", "ogden", "--preset", "skin", "--param", "nu=0.5", "--no-fe"], "nu = 0.5"),
    (["material", "neo-hookean", "--param", "E_MPa=1", "--param", "nu=0.6", "--no-fe"],
     "nu = 0.6"),
    (["material", "ogden", "--preset", "skin", "--stretch", "a:b:c", "--no-fe"], "--stretch"),
])
def test_bad_input_clear_error(argv, needle):
    code, out, err = run(argv)
    assert code == 2
    assert needle in err
    assert "Traceback" not in err


def test_drucker_option():
    code, out, _ = run(["material", "ogden", "--preset", "skin", "--drucker", "0.5:2.0"])
    assert code == 0 and "equibiaxial: UNSTABLE" in out


def test_help_mentions_units():
    code, out, _ = run(["material", "--help"])
    assert code == 0 and "MPa" in out and "pure shear" in out


def test_first_run_compiles_quietly(tmp_path):
    # a fresh machine: an empty form cache. The compiler's INFO log ("running build_ext", gcc
    # command lines) stays off the console. (The cube's Ogden forms compile at -O0 here,
    # handfe.solver.FAST_COMPILE: ~20 s against ~4 min at gcc -O2; no timed assert.)
    import os
    import subprocess
    import sys

    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path))
    proc = subprocess.run([sys.executable, "-m", "handfe.cli", "material", "ogden", "--preset",
                           "skin", "--mode", "uniaxial", "--stretch", "0.9:1.1:3",
                           "--incompressible"], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert any((tmp_path / "fenics").glob("libffcx_forms_*.c"))  # it did compile
    assert "INFO" not in proc.stderr + proc.stdout
    assert "gcc" not in proc.stderr + proc.stdout
    rows = proc.stdout.strip().splitlines()
    assert rows[0].startswith("stretch,") and len(rows) == 4

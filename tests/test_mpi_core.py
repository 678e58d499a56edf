"""Distributed (MPI.COMM_WORLD) solves equal the serial (MPI.COMM_SELF) ones to 1e-8 relative.
Run by `make test-mpi` under mpirun -n 2 (and trivially in the serial suite)."""

import numpy as np
import pytest
from mpi4py import MPI

from handfe.materials import MooneyRivlin, NeoHookean, Ogden, homogeneous
from handfe.solver import Discretisation
from handfe.verification import cook_membrane, cube_stress_curve

pytestmark = pytest.mark.mpi


def test_cook_membrane_ranks_agree():
    mat = NeoHookean.from_E_nu(1.0, 0.49)
    par = cook_membrane(MPI.COMM_WORLD, 6, mat, Discretisation("taylor-hood"))
    ser = cook_membrane(MPI.COMM_SELF, 6, mat, Discretisation("taylor-hood"))
    assert par == pytest.approx(ser, rel=1e-8)


@pytest.mark.parametrize("mat", [Ogden.skin(), MooneyRivlin.fingertip_mean()],
                         ids=["ogden", "mooney-rivlin"])
def test_cube_ranks_agree(mat):
    lams = [0.7, 1.4]
    par = cube_stress_curve(mat, "uniaxial", lams, comm=MPI.COMM_WORLD, n=2)
    ser = cube_stress_curve(mat, "uniaxial", lams, comm=MPI.COMM_SELF, n=2)
    np.testing.assert_allclose(par, ser, rtol=1e-8)
    cf = [homogeneous(mat, "uniaxial", x)[0] for x in lams]
    np.testing.assert_allclose(par, cf, rtol=1e-6)

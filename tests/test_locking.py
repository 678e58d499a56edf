"""Locking: Cook's membrane in plane strain, neo-Hookean, nu = 0.49 and 0.499.

Mean tip deflection (mm), measured with handfe.verification.cook_membrane (E = 1 MPa, 0.5 N):
  nu = 0.499  taylor-hood n=2,4,8,16: 6.79, 7.74, 8.01, 8.11   (converging)
              p1          n=2..32:    2.55, 2.63, 2.77, 3.16, 4.09 (locked: ~1/3 of the answer)
The mixed formulation converges under refinement; plain P1 visibly does not."""

import pytest
from mpi4py import MPI

from handfe.materials import NeoHookean
from handfe.solver import Discretisation
from handfe.verification import cook_membrane


@pytest.mark.parametrize("nu", [0.49, 0.499])
def test_taylor_hood_converges_p1_locks(nu):
    mat = NeoHookean.from_E_nu(1.0, nu)
    th = [cook_membrane(MPI.COMM_SELF, n, mat, Discretisation("taylor-hood")) for n in (2, 4, 8)]
    p1 = [cook_membrane(MPI.COMM_SELF, n, mat, Discretisation("p1")) for n in (2, 4, 8)]
    # mixed: monotone, increments shrink by > 2x per refinement, within 5 % at n = 8
    assert th[0] < th[1] < th[2]
    assert abs(th[2] - th[1]) < 0.5 * abs(th[1] - th[0])
    assert abs(th[2] - th[1]) / th[2] < 0.05
    # P1 on the finest mesh is still far stiffer than the coarsest mixed mesh
    assert p1[2] < 0.5 * th[2]
    assert p1[2] < th[0]
    # and its refinement error barely moves: after 2 refinements it is still > 50 % off
    assert (th[2] - p1[2]) / th[2] > 0.5

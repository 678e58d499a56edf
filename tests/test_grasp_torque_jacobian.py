"""The torque tangent of the muscles mode (:func:`handfe.grasp.fe.condensed_torque_jacobian`:
the FE tangent condensed onto bone rotations) against central finite differences of the bone
torques, each difference from two full Newton solves. A block of Ogden skin (p1-p1s, NumPy
kernel) is fixed at its base (wrist tag 90), tied at its top to two rigid "bones" that two
joints turn (a chain, as a finger's joints), and rests on a linear foundation on one side
(standing in for the contact form). Runs on 1 and 2 ranks."""

from types import SimpleNamespace

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from handfe.grasp.fe import (
    SKIN,
    BoneBC,
    GraspProblem,
    TwoFormNewton,
    condensed_torque_jacobian,
    torques_from,
)
from handfe.materials import Ogden

# a chain of two joints above the block: joint 0 (axis y) turns both bones "p" (x < 5) and
# "d" (x > 5) of the top face, joint 1 (axis tilted in the x-y plane, turning with joint 0)
# turns "d" only - as a finger's MCP and PIP
A0, C0 = np.array([0.0, 1.0, 0.0]), np.array([5.0, 3.0, 14.0])
A1, C1 = np.array([0.6, 0.8, 0.0]), np.array([7.0, 3.0, 9.0])
DISTAL = [["p", "d"], ["d"]]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _chain(angles) -> tuple[dict, list]:
    """Bone motions {bone: (R, t)} (x_new = R x + t) and the current joint (axis, centre)."""
    Q0, Q1 = _rotation(A0, angles[0]), _rotation(A1, angles[1])
    motions = {"p": (Q0, C0 - Q0 @ C0),
               "d": (Q0 @ Q1, Q0 @ (C1 - Q1 @ C1 - C0) + C0)}
    return motions, [(A0, C0), (Q0 @ A1, Q0 @ (C1 - C0) + C0)]


@pytest.mark.mpi
def test_condensed_torque_jacobian_matches_finite_differences():
    comm = MPI.COMM_WORLD
    msh = mesh.create_box(comm, [np.zeros(3), np.array([10.0, 6.0, 4.0])], [5, 3, 2],
                          mesh.CellType.tetrahedron)
    nc = msh.topology.index_map(3).size_local
    ct = mesh.meshtags(msh, 3, np.arange(nc, dtype=np.int32), np.full(nc, SKIN, np.int32))
    top_p = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 4.0) & (x[0] < 5))
    top_d = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 4.0) & (x[0] > 5))
    base = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 0.0))
    side = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[0], 10.0))
    f = np.concatenate([top_p, top_d, base, side]).astype(np.int32)
    v = np.concatenate([np.full(len(top_p), 5), np.full(len(top_d), 6), np.full(len(base), 90),
                        np.full(len(side), 7)]).astype(np.int32)
    order = np.argsort(f)
    ft = mesh.meshtags(msh, 2, f[order], v[order])
    model = SimpleNamespace(mesh=msh, cell_tags=ct, facet_tags=ft, tags={"bone_p": 5, "bone_d": 6})
    skin = Ogden.skin(nu=0.49)
    problem = GraspProblem(model, skin, skin, element="p1-p1s")
    bc = BoneBC(problem, model, ["p", "d"])
    ds = ufl.Measure("ds", domain=msh, subdomain_data=ft)
    k = fem.Constant(msh, 1e-3)  # MPa/mm: a soft foundation on the x = 10 face
    problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=40)

    def solve(angles) -> np.ndarray:
        old = bc.ubc.x.array.copy()
        motions, axes = _chain(angles)
        bc.set(motions)
        bc.predict(old)
        ok, its, reason = solver.solve()
        assert ok, reason
        R = solver.full_residual()
        t = torques_from(R.getArray(), bc, axes, DISTAL, comm)
        R.destroy()
        return t

    theta = np.radians([3.0, -2.0])  # a finitely strained state (shear ~ 15 %)
    solve(theta)
    w0 = problem.w.x.array.copy()
    Jm = condensed_torque_jacobian(solver, bc, _chain(theta)[1], DISTAL, comm)
    h = 1e-3
    Jfd = np.zeros((2, 2))
    for i in range(2):
        d = np.zeros(2)
        d[i] = h
        tp = solve(theta + d)
        problem.w.x.array[:] = w0
        bc.set(_chain(theta)[0])
        tm = solve(theta - d)
        problem.w.x.array[:] = w0
        bc.set(_chain(theta)[0])
        Jfd[:, i] = (tp - tm) / (2 * h)
    assert np.abs(Jfd).max() > 0.0
    assert np.allclose(Jm, Jfd, rtol=0.0, atol=2e-4 * np.abs(Jfd).max()), (Jm, Jfd)
    # the joints resist their own rotation (negative diagonal: a restoring torque)
    assert Jm[0, 0] < 0.0 and Jm[1, 1] < 0.0

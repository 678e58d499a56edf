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


def _block(comm):
    """A 10 x 6 x 4 mm block of Ogden skin (p1-p1s): base fixed (wrist tag 90), the top face
    split into two rigid "bones" p (x < 5) and d (x > 5), the x = 10 face tagged 7 for a
    foundation. Returns (mesh, problem, bone BC, ds)."""
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
    return msh, problem, bc, ds


@pytest.mark.mpi
def test_condensed_torque_jacobian_matches_finite_differences():
    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
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


@pytest.mark.mpi
def test_condensed_tangent_of_the_object_translation_matches_finite_differences():
    # the side face rests on a spring foundation that moves with an "object" translated by t
    # (R depends on u - t there, as the contact does): the tangent with respect to t and the
    # object force (sum of R) from condensed_tangent(translate=True) against central
    # differences of full solves; the state response du/dt is the predictor of a move
    from handfe.grasp.fe import condensed_tangent

    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 1e-3)
    t = fem.Constant(msh, np.array([0.5, -0.3, 0.2]))
    u = ufl.split(problem.w)[0]
    # a stiffening foundation (k (1 + |u - t|^2) (u - t)): a nonlinear "contact"
    d = u - t
    problem.add_residual(k * (1.0 + ufl.inner(d, d)) * ufl.inner(d, problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=40)
    theta = np.radians([3.0, -2.0])
    motions, axes = _chain(theta)

    def solve(tt) -> tuple[np.ndarray, np.ndarray]:
        t.value = tt
        ok, its, reason = solver.solve()
        assert ok, reason
        R = solver.full_residual()
        r = R.getArray()
        tq = torques_from(r, bc, axes, DISTAL, comm)
        F = np.array(comm.allreduce(np.array([r[x].sum() for x in bc.all_comp_dofs]),
                                    op=MPI.SUM))
        R.destroy()
        return tq, F

    old = bc.ubc.x.array.copy()
    bc.set(motions)
    bc.predict(old)
    t0 = t.value.copy()
    solve(t0)
    w0 = problem.w.x.array.copy()
    T = condensed_tangent(solver, bc, axes, DISTAL, comm, translate=True)
    Jtheta = condensed_torque_jacobian(solver, bc, axes, DISTAL, comm)
    assert np.allclose(T.torque_theta, Jtheta)
    h = 1e-3
    tq_fd, F_fd = np.zeros((2, 3)), np.zeros((3, 3))
    n = len(T.response_t[0])
    for c in range(3):
        e = np.zeros(3)
        e[c] = h
        tp, Fp = solve(t0 + e)
        wp = problem.w.x.array[:n].copy()
        problem.w.x.array[:] = w0
        tm, Fm = solve(t0 - e)
        wm = problem.w.x.array[:n].copy()
        problem.w.x.array[:] = w0
        tq_fd[:, c], F_fd[:, c] = (tp - tm) / (2 * h), (Fp - Fm) / (2 * h)
        dw = (wp - wm) / (2 * h)
        scale = comm.allreduce(float(np.abs(dw).max()), op=MPI.MAX)
        err = comm.allreduce(float(np.abs(T.response_t[c] - dw).max()), op=MPI.MAX)
        assert err <= 1e-3 * scale, (c, err, scale)
    assert np.allclose(T.torque_t, tq_fd, rtol=0.0, atol=1e-3 * np.abs(tq_fd).max())
    assert np.allclose(T.force_t, F_fd, rtol=0.0, atol=1e-3 * np.abs(F_fd).max())
    # moving the object into the foundation's direction pulls the object back: F_xx < 0
    assert T.force_t[0, 0] < 0.0
    # the object force's theta derivative against differences of the joint angles
    F_th = np.zeros((3, 2))
    for i in range(2):
        dth = np.zeros(2)
        dth[i] = h
        out = []
        for sgn in (1.0, -1.0):
            old = bc.ubc.x.array.copy()
            bc.set(_chain(theta + sgn * dth)[0])
            bc.predict(old)
            out.append(solve(t0)[1])
            problem.w.x.array[:] = w0
            bc.set(motions)
        F_th[:, i] = (out[0] - out[1]) / (2 * h)
    assert np.allclose(T.force_theta, F_th, rtol=0.0, atol=1e-3 * np.abs(F_th).max())


@pytest.mark.mpi
def test_tangent_predictor_of_a_joint_step_is_first_order_exact():
    # solver.tangent_predictor: the state moved by the condensed tangent's response to a joint
    # step (GraspFE._tangent_prediction) leaves a residual O(step^2), while the elastic
    # extension of the bone motion leaves O(step) against a stiff, nonlinear foundation
    # (standing in for loaded pads)
    from handfe.grasp.fe import condensed_tangent
    from handfe.grasp.scene import GraspFE

    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 0.05)  # MPa/mm: 50x the Jacobian test's foundation
    u = ufl.split(problem.w)[0]
    problem.add_residual(k * (1.0 + ufl.inner(u, u)) * ufl.inner(u, problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=40)
    theta = np.radians([3.0, -2.0])
    bc.set(_chain(theta)[0])
    ok, _, reason = solver.solve()
    assert ok, reason
    w0 = problem.w.x.array.copy()
    bc0 = bc.ubc.x.array.copy()
    T = condensed_tangent(solver, bc, _chain(theta)[1], DISTAL, comm, responses=True)
    assert len(T.response_theta) == 2
    scene = SimpleNamespace(_theta_response=T.response_theta, bc=bc, problem=problem,
                            solver=solver)

    def residual() -> float:
        return GraspFE._residual_norm(scene)

    r_ext, r_tan = [], []
    for h in (np.radians([1.0, -1.5]), np.radians([0.5, -0.75])):
        problem.w.x.array[:] = w0
        problem.w.x.scatter_forward()
        bc.set(_chain(theta + h)[0])
        bc.predict(bc0)
        ext = problem.w.x.array.copy()
        r_ext.append(residual())
        problem.w.x.array[:] = GraspFE._tangent_prediction(scene, w0, ext, h)
        problem.w.x.scatter_forward()
        r_tan.append(residual())
        bc.set(_chain(theta)[0])
    assert r_tan[0] < 0.1 * r_ext[0], (r_tan, r_ext)
    assert r_ext[0] / r_ext[1] < 2.5  # first order
    assert r_tan[0] / r_tan[1] > 3.0  # second order: halving the step quarters it

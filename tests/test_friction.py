"""Regularised Coulomb friction of the contact engine (handfe.contact_problem.RigidContact).

Scene: an elastic block 4 x 4 x 1 mm (neo-Hookean, E = 1 MPa, nu = 0.3, P2 tets on a 4x4x2 box
mesh) stands on a rigid plate z <= 0 (the same ``HalfSpace`` as the other contact tests, so
the compiled forms are shared). Its top face is clamped to a rigid "platen" that is

1. pressed down by DELTA = 0.1 mm (normal force N ~ 2.2 N, measured), then
2. moved tangentially along +x by d (displacement control, so sliding has an equilibrium).

Forces are taken from the consistent reaction on the clamped top face
(``HyperelasticProblem.reaction``): by equilibrium the plate pushes on the block with
N = -R_z and the friction force is F_t = -(R_x, R_y). The slip of the contact face is the mean
x displacement of the bottom face's vertices (the plate does not move).

Stick spring k_t = k_n = 10 E / h (automatic penalty): the regularised law lets a stuck face
creep by |t_T| / k_t, so "stick" is asserted as slip << d, not slip = 0.
"""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from handfe.errors import InputError

L_MM, H_MM = 4.0, 1.0
DELTA = 0.1  # mm, platen travel into the plate
PEN_TOL = 2e-4  # mm: Uzawa loop tolerance, small against DELTA so N does not drift
E_MPA, NU = 1.0, 0.3


def _block(comm, cells: tuple[int, int, int] = (4, 4, 2)):
    from dolfinx import mesh

    msh = mesh.create_box(comm, [np.array([-L_MM / 2, -L_MM / 2, 0.0]),
                                 np.array([L_MM / 2, L_MM / 2, H_MM])], list(cells),
                          mesh.CellType.tetrahedron)
    fdim = 2
    bot = mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[2], 0.0))
    top = mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[2], H_MM))
    idx = np.concatenate([bot, top]).astype(np.int32)
    val = np.concatenate([np.full(len(bot), 1), np.full(len(top), 2)]).astype(np.int32)
    order = np.argsort(idx)
    return msh, mesh.meshtags(msh, fdim, idx[order], val[order])


class BlockScene:
    """Block on a plate (or on ``obstacle``, a rigid shape below z = 0), top clamped to a platen
    moved by ``platen`` (mm)."""

    def __init__(self, mu: float, comm=MPI.COMM_WORLD, augmented_friction: bool = False,
                 element: str = "p2", obstacle=None, cells: tuple[int, int, int] = (4, 4, 2),
                 penalty_factor: float = 10.0):
        from handfe.contact import HalfSpace
        from handfe.contact_problem import RigidContact
        from handfe.materials import NeoHookean
        from handfe.solver import Discretisation, HyperelasticProblem

        self.comm = comm
        self.mu = mu
        self.mesh, self.ft = _block(comm, cells)
        self.prob = HyperelasticProblem(self.mesh, NeoHookean.from_E_nu(E_MPA, NU),
                                        disc=Discretisation(element))
        self.top = self.ft.find(2)
        self.platen = self.prob.fix(self.top)
        plate = HalfSpace(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0))
        self.contact = RigidContact(self.prob, plate if obstacle is None else obstacle, self.ft,
                                    1, mu=mu, penetration_tol_mm=PEN_TOL,
                                    augmented_friction=augmented_friction, stick_ratio=0.3,
                                    penalty_factor=penalty_factor)
        x = self.mesh.geometry.x
        self._bottom_nodes = np.flatnonzero(np.isclose(x[:, 2], 0.0))

    def move(self, target, initial: float = 0.25):
        """Move the platen linearly from its current position to ``target`` (3-vector, mm)."""
        from handfe.solver import LoadStepping, solve

        start = self.platen.value.copy()
        target = np.asarray(target, dtype=float)

        def set_load(t: float) -> None:
            self.contact.apply_history()
            self.platen.value = start + t * (target - start)

        def on_step(t: float, res) -> None:
            self.contact.on_step(t, res, defer=True)

        return solve(self.prob, set_load, augment=self.contact.augment, on_step=on_step,
                     stepping=LoadStepping(initial=initial, min_step=1.0 / 256,
                                           max_step=initial))

    def forces(self) -> tuple[float, np.ndarray]:
        """(N, friction force vector in the plate plane) on the block, from the reaction (N)."""
        R = self.prob.reaction(self.top)
        return float(-R[2]), -R[:2]

    def slip_mm(self) -> float:
        """Mean x displacement of the bottom-face vertices (mm), averaged over ranks."""
        from handfe.contact import _node_values, _to_p1

        u1 = _to_p1(self.prob.displacement(), self.mesh, (3,))
        ux = _node_values(u1, self.mesh)[self._bottom_nodes, 0]
        n_own = self.mesh.geometry.index_map().size_local
        own = self._bottom_nodes < n_own
        s = self.comm.allreduce(float(ux[own].sum()), op=MPI.SUM)
        n = self.comm.allreduce(int(own.sum()), op=MPI.SUM)
        return s / n


def _pressed(mu: float, augmented_friction: bool = False) -> BlockScene:
    sc = BlockScene(mu, augmented_friction=augmented_friction)
    sc.move((0.0, 0.0, -DELTA), initial=0.5)
    return sc


@pytest.mark.parametrize("mu", [0.74, 0.3])
def test_sticks_below_mu_N(mu):
    """A tangential platen travel giving |F_t| ~ 0.3-0.5 mu N: the contact face sticks (its
    slip is the stick spring's creep, < 10 % of the platen travel, the rest is elastic shear of
    the block) and |F_t| < mu N."""
    sc = _pressed(mu)
    N0, _ = sc.forces()
    assert N0 > 1.0
    d = 0.08 * mu / 0.74  # mm
    sc.move((d, 0.0, -DELTA))
    N, Ft = sc.forces()
    ft = float(np.linalg.norm(Ft))
    assert 0.15 * mu * N < ft < 0.6 * mu * N
    assert Ft[0] < 0.0  # the platen moved +x: the plate holds the block back
    slip = sc.slip_mm()
    assert 0.0 <= slip < 0.1 * d
    # elastic shear of the block carries the rest: |F_t| ~ G A / H * (d - slip) within 25 %
    G = E_MPA / (2 * (1 + NU))
    assert ft == pytest.approx(G * L_MM**2 / H_MM * (d - slip), rel=0.25)


@pytest.mark.parametrize("mu", [0.74, 0.3])
def test_slides_above_mu_N(mu):
    """Platen travel far beyond the stick limit: the face slides (its travel grows with the
    platen's, one for one) and the friction force is bounded by mu N."""
    sc = _pressed(mu)
    d1 = 0.6 * mu / 0.74
    sc.move((d1, 0.0, -DELTA), initial=0.125)
    s1 = sc.slip_mm()
    N1, F1 = sc.forces()
    d2 = d1 + 0.2
    sc.move((d2, 0.0, -DELTA), initial=0.25)
    s2 = sc.slip_mm()
    N2, F2 = sc.forces()
    for N, F in ((N1, F1), (N2, F2)):
        assert np.linalg.norm(F) <= mu * N * (1 + 1e-6)
        assert np.linalg.norm(F) >= 0.85 * mu * N
    assert s1 > 0.3 * d1
    # N still rises while the block slides (it tilts), so the shear grows a little too: the
    # face follows the platen to within 25 % (ahead of it when N falls and the shear relaxes)
    assert 0.75 * (d2 - d1) < s2 - s1 < 1.1 * (d2 - d1)


@pytest.mark.xfail(strict=True, reason=(
    "nodal (P2) stick anchor vs quadrature-point stick/slip decision (see "
    "test_contact_equilibrium): in steady sliding parts of the face fall back to the stick "
    "spring and |F_t| = 0.89 mu N instead of mu N (mu = 0.3 reaches 0.998 mu N)"))
def test_sliding_force_equals_mu_N():
    mu = 0.74
    sc = _pressed(mu)
    sc.move((0.6, 0.0, -DELTA), initial=0.125)
    N, F = sc.forces()
    assert np.linalg.norm(F) == pytest.approx(mu * N, rel=0.02)


def test_augmented_friction_sticks_without_creep():
    """Augmented friction (tangential Uzawa multipliers, stick spring 0.3 k_n): below mu N the
    face sticks to within the stick tolerance (PEN_TOL = 2e-4 mm), not by a creep |t_T| / k_t,
    and the friction force is the elastic shear of the block, G A / H * d, within 25 %."""
    mu = 0.74
    sc = _pressed(mu, augmented_friction=True)
    d = 0.08
    sc.move((d, 0.0, -DELTA))
    N, Ft = sc.forces()
    ft = float(np.linalg.norm(Ft))
    assert ft < 0.6 * mu * N and Ft[0] < 0.0
    assert abs(sc.slip_mm()) < 2 * PEN_TOL
    assert sc.contact.last_creep_mm <= PEN_TOL
    G = E_MPA / (2 * (1 + NU))
    assert ft == pytest.approx(G * L_MM**2 / H_MM * d, rel=0.25)


def _contact_force(sc: BlockScene) -> np.ndarray:
    """Sum of the contact residual over the block's dofs (N, all ranks): the force the plate
    exerts on the block as the contact data of the current state give it."""
    from dolfinx import fem
    from dolfinx.fem import petsc as fem_petsc
    from petsc4py import PETSc

    b = fem_petsc.assemble_vector(fem.form(sc.contact.terms.residual))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    n_owned = sc.prob.W.dofmap.index_map.size_local * sc.prob.W.dofmap.index_map_bs
    arr = b.getArray(readonly=True)
    out = []
    for i in range(3):
        d = np.unique(sc.prob.displacement_space.sub(i).dofmap.list.array)
        out.append(sc.comm.allreduce(float(arr[d[d < n_owned]].sum()), op=MPI.SUM))
    b.destroy()
    return -np.array(out)


def test_reported_stuck_state_balances_its_friction_data():
    """The return mapping of the last step (on_step) changes the stick multipliers; applied
    at once, the contact's friction force of the final, stuck state was 3.4 % off the support
    reaction (0.478 vs 0.462 N). Deferred to the next solve, the two agree."""
    sc = _pressed(0.74, augmented_friction=True)
    sc.move((0.08, 0.0, -DELTA))
    N, Ft = sc.forces()
    fc = _contact_force(sc)
    assert sc.contact.history_due
    assert fc[2] == pytest.approx(N, rel=1e-6)
    assert fc[:2] == pytest.approx(Ft, rel=1e-6, abs=1e-8 * N)
    sc.contact.apply_history()  # what a next step would start from: no longer balanced
    assert abs(_contact_force(sc)[0] - Ft[0]) > 1e-3 * abs(Ft[0])


def test_an_update_right_after_the_return_mapping_can_leave_lambda_t_to_it():
    """The return mapping (on_step) is lambda_t <- t_T of the solved state. An Uzawa update
    right after it with ``tangential=False`` keeps that; the default would set lambda_t <- t_T
    again, evaluated with the mapped data, which adds each stuck node's stick correction
    k_t x slip a second time (GraspFE.augment with solver.uzawa_tangential_relax < 1)."""
    sc = _pressed(0.74, augmented_friction=True)
    sc.move((0.08, 0.0, -DELTA))
    c = sc.contact
    d = c._t_dofs

    def lam_t() -> np.ndarray:
        return c.lambda_t.x.array.reshape(-1, 3)[d].copy()

    def norm(a: np.ndarray) -> float:
        return float(np.sqrt(sc.comm.allreduce(float(np.sum(a * a)), op=MPI.SUM)))

    lam0, tT = lam_t(), c._tangential()[d].copy()
    assert c.history_due
    c.apply_history()
    mapped = lam_t()
    assert norm(mapped - tT) <= 1e-12 * norm(tT)  # the mapping: lambda_t <- t_T
    c.penetration_tol_mm = c.stick_tol_mm = 0.0  # force an update
    done, _ = c.augment(True, tangential=False)
    assert not done
    assert norm(lam_t() - mapped) == 0.0
    # what a second lambda_t <- t_T would add: the stick correction once more (measured 0.98
    # of it: almost every node of the block sticks)
    again = c._tangential()[d] - mapped
    assert norm(again) > 0.5 * norm(tT - lam0) > 0.0


@pytest.mark.xfail(strict=True, reason=(
    "measured 0.886 mu N (1.593 N for mu N = 1.798 N), the same shortfall as the penalty law: "
    "the nodal multiplier does not fix the quadrature-point stick/slip mix at the patch"))
def test_augmented_friction_slides_at_mu_N():
    """Augmented friction in steady sliding should give a friction force of mu N."""
    mu = 0.74
    sc = _pressed(mu, augmented_friction=True)
    sc.move((0.6, 0.0, -DELTA), initial=0.125)
    N, F = sc.forces()
    assert np.linalg.norm(F) <= mu * N * (1 + 1e-6)
    assert np.linalg.norm(F) == pytest.approx(mu * N, rel=0.02)


def test_stick_persists_when_load_is_held():
    """Regression: the stick anchor used to restart from zero traction every load step, so a
    held, stuck block relaxed (0.276 -> 0.271 N) and crept; the return mapping keeps it."""
    sc = _pressed(0.74)
    sc.move((0.05, 0.0, -DELTA))
    _, F0 = sc.forces()
    s0 = sc.slip_mm()
    for _ in range(3):  # same platen position, three more load steps
        sc.move((0.05, 0.0, -DELTA), initial=1.0)
    _, F1 = sc.forces()
    assert np.linalg.norm(F1) == pytest.approx(np.linalg.norm(F0), rel=2e-3)
    assert sc.slip_mm() == pytest.approx(s0, abs=1e-4)


def test_frictionless_gives_no_tangential_force():
    """mu = 0: the platen drags the block along without any tangential force."""
    sc = _pressed(0.0)
    N0, _ = sc.forces()
    sc.move((0.3, 0.0, -DELTA))
    N, F = sc.forces()
    assert N == pytest.approx(N0, rel=5e-3)
    assert np.linalg.norm(F) < 1e-8 * N
    assert sc.slip_mm() == pytest.approx(0.3, rel=1e-3)
    m = sc.contact.metrics()
    assert m.tangential_force_N == 0.0


@pytest.mark.mpi
def test_friction_ranks_agree():
    """Press, stick and slide on COMM_WORLD equal the serial solve (COMM_SELF) to 1e-6."""

    def run(comm):
        sc = BlockScene(0.74, comm)
        sc.move((0.0, 0.0, -DELTA), initial=0.5)
        out = []
        for d in (0.08, 0.6):
            sc.move((d, 0.0, -DELTA), initial=0.125)
            N, F = sc.forces()
            out += [N, F[0], sc.slip_mm()]
        return np.array(out)

    ser = run(MPI.COMM_SELF)
    par = ser if MPI.COMM_WORLD.size == 1 else run(MPI.COMM_WORLD)
    np.testing.assert_allclose(par, ser, rtol=1e-6, atol=1e-9)


def test_release_stick_after_a_frictionless_solve_starts_stick_afresh():
    """``set_friction(0)`` + a solve + ``release_stick``: the sheared, stuck block lets go of
    its shear (the face follows the platen, no tangential force), and friction is back on for
    the next load: a further platen travel shears the block from the released state (G A / H
    times the new travel, within 25 %) - the muscles mode's ``muscle_frictionless_closing``."""
    mu = 0.74
    sc = _pressed(mu, augmented_friction=True)
    d = 0.08
    sc.move((d, 0.0, -DELTA))
    N, Ft = sc.forces()
    assert np.linalg.norm(Ft) > 0.15 * mu * N
    sc.contact.apply_history()
    sc.contact.set_friction(0.0)
    sc.move((d, 0.0, -DELTA), initial=1.0)
    sc.contact.release_stick()
    sc.contact.set_friction(mu)
    N1, F1 = sc.forces()
    assert np.linalg.norm(F1) < 1e-6 * N1
    assert sc.slip_mm() == pytest.approx(d, rel=1e-2)
    assert np.linalg.norm(_contact_force(sc)[:2]) < 1e-6 * N1  # the data balance the state
    s1 = sc.slip_mm()
    sc.move((d + 0.04, 0.0, -DELTA))
    N2, F2 = sc.forces()
    G = E_MPA / (2 * (1 + NU))
    assert abs(sc.slip_mm() - s1) < 2 * PEN_TOL
    assert np.linalg.norm(F2) == pytest.approx(G * L_MM**2 / H_MM * 0.04, rel=0.25)
    with pytest.raises(InputError, match="mu = -1"):
        sc.contact.set_friction(-1.0)


def _penalty_pressed(shear_mm: float, **scene) -> BlockScene:
    """Pressed by DELTA and sheared (stuck) by ``shear_mm`` on the penalty alone (no Uzawa
    updates: the tolerances are out of reach), so the face penetrates. P1, as the grasp: the
    multipliers live at the vertices, where a P1 face's gap on the plate is exact."""
    sc = BlockScene(0.74, augmented_friction=True, element="p1", **scene)
    sc.contact.penetration_tol_mm = sc.contact.stick_tol_mm = 10.0
    sc.move((0.0, 0.0, -DELTA), initial=0.5)
    sc.move((shear_mm, 0.0, -DELTA), initial=0.5)
    sc.contact.apply_history()
    return sc


def test_stiffen_keeps_the_tractions_and_stiffens_what_follows():
    """``RigidContact.stiffen(8 k)`` on a penetrating, stuck block: the contact force of the
    state (normal and friction) is unchanged, so the state stays balanced; a further press
    then penetrates by much less than with the old penalty (the muscles mode raises the penalty
    this way as the pads' pressure grows)."""
    d, press = 0.04, 0.02
    sc = _penalty_pressed(d)
    F0 = _contact_force(sc)
    pen0 = sc.contact.uzawa.penetration()
    assert pen0 > 1e-3 and abs(F0[0]) > 0.1 * abs(F0[2])  # penetrating and sheared
    k = float(sc.contact.k_n.value)
    sc.contact.stiffen(8.0 * k)
    assert float(sc.contact.k_n.value) == pytest.approx(8.0 * k)
    np.testing.assert_allclose(_contact_force(sc), F0, rtol=0.0, atol=1e-6 * abs(F0[2]))
    sc.move((d, 0.0, -DELTA - press))
    ref = _penalty_pressed(d)
    ref.move((d, 0.0, -DELTA - press))
    grow, grow_ref = (s.contact.uzawa.penetration() - pen0 for s in (sc, ref))
    assert grow < 0.3 * grow_ref
    # pressing deeper by `press` adds about the same force either way (the tissue decides)
    assert _contact_force(sc)[2] == pytest.approx(_contact_force(ref)[2], rel=0.2)
    sc.contact.stiffen(k)  # not above the penalty: nothing changes
    assert float(sc.contact.k_n.value) == pytest.approx(8.0 * k)


def _contact_residual(sc: BlockScene) -> np.ndarray:
    """The contact residual vector (owned dofs of this rank, N)."""
    from dolfinx import fem
    from dolfinx.fem import petsc as fem_petsc
    from petsc4py import PETSc

    b = fem_petsc.assemble_vector(fem.form(sc.contact.terms.residual))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    arr = b.getArray(readonly=True).copy()
    b.destroy()
    return arr


def _global_norm(comm, a: np.ndarray) -> float:
    return float(np.sqrt(comm.allreduce(float(a @ a), op=MPI.SUM)))


@pytest.mark.mpi
def test_stiffen_on_a_curved_object_keeps_the_nodal_forces():
    """On a ball the interior of a flat facet is deeper than its nodes (sagitta a^2 / 8R =
    6 um for 0.5 mm facets on R = 5 mm), so keeping the nodal trial pressures (lambda - k g)
    alone does not keep the Gauss-point pressures: x4 on a block pressed 0.08 mm into the
    ball raised its normal force by ~30 % (measured), and a grasp's first solve after the
    stiffening started from a residual of 16-25 N. The force-matching sweeps keep every nodal
    normal force to ~1 % and the contact residual vector to a few %."""
    from handfe.contact import Sphere

    R = 5.0
    scene = {"obstacle": Sphere(centre=(0.0, 0.0, -R), radius=R), "cells": (8, 8, 2),
             "penalty_factor": 0.3}  # a soft penalty: penetration >> sagitta, as on the hand
    sc = _penalty_pressed(0.02, **scene)
    assert sc.contact.uzawa.penetration() > 0.05
    r0, F0 = _contact_residual(sc), _contact_force(sc)
    k = float(sc.contact.k_n.value)
    lam, u_ref = sc.contact.lambda_n.x.array.copy(), sc.contact.u_ref.x.array.copy()

    def change() -> tuple[float, np.ndarray]:
        dr = _contact_residual(sc) - r0
        return _global_norm(sc.comm, dr) / _global_norm(sc.comm, r0), _contact_force(sc)

    assert sc.contact.stiffen(4.0 * k, match_forces=False) == 0.0
    rel_nodal, F_nodal = change()
    assert F_nodal[2] > 1.2 * F0[2] and rel_nodal > 0.2  # the sagitta's pressure
    sc.contact.lambda_n.x.array[:] = lam
    sc.contact.u_ref.x.array[:] = u_ref
    sc.contact.set_penalty(k)
    off = sc.contact.stiffen(4.0 * k)
    rel, F = change()
    assert float(sc.contact.k_n.value) == pytest.approx(4.0 * k)
    assert off < 0.02 and rel < 0.03
    assert F[2] == pytest.approx(F0[2], rel=0.01)
    assert F[0] == pytest.approx(F0[0], rel=0.05)  # friction: stick anchors scaled

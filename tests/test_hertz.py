"""Hertz contact: the contact engine against F = 4/3 E* sqrt(R) delta^1.5, a = sqrt(R delta).

Set-up. A rigid sphere (``handfe.contact.Sphere``, R = 10 mm) is pressed delta = 0.1 mm
(delta/R = 1 %) into a neo-Hookean block (E = 1 MPa, nu = 0.3, small strain, P2). Hertz's
formulas hold for either body being the rigid one (E* = E/(1 - nu^2) collects both), so this is
the brief's sphere-on-plate problem with the roles swapped. The reason is Hertz's half-space
assumption: delta is the approach of points far from the contact. An elastic hemisphere is
measurably stiffer than that (same engine, delta/R = 1.5 %: +6.5 % force with a symmetry plane
at the equator, +9 % with the equator clamped — finite-body effects of order sqrt(delta/R),
not contact errors), whereas a block large against the contact (a quarter of a 200 mm cube,
clamped at the bottom, rollers on the symmetry planes x = 0 and y = 0, a = 1 mm) is a
half-space to < 1 %. Mesh: gmsh on rank 0, element size 0.2 mm (a/5) within 1.2 mm of the
contact point, growing 0.4 mm per mm to 40 mm.

Measured quantities.
* Force: 4 x the consistent reaction on the clamped bottom (quarter model); also the contact
  metrics' normal force.
* Contact radius, from the contact pressure (not from the gap tolerance, which overestimates
  a where the gap opens as (r - a)^1.5): the nodal Uzawa multipliers lambda_n (= the nodal
  contact pressure of the converged state) are fitted by least squares with the Hertz form
  p^2 = p0^2 (1 - r^2/a^2) over the pressure-positive nodes inside 0.8 of the patch; a is
  where the fit vanishes. The radius of the outermost node with positive pressure is checked
  too, to within one quarter of the local element size (5 %).
* Penetration <= 0.01 mm (``ContactMetrics.max_penetration_mm``).

Numbers (this mesh, 1 rank; penetration at the six nodes of each facet, the radius from the
multiplier's nodes): P1 multipliers (vertices) force +1.4 % (reaction) / +1.6 % (metrics),
fitted radius -0.5 %, outermost pressure node +3.9 %, penetration 2.9e-4 mm; P2 multipliers
(vertices and edge midpoints) +1.5 % / +1.7 %, -0.3 %, +3.9 %, 1.3e-4 mm.
Reproduce: ``.venv/bin/pytest -q -s tests/test_hertz.py``.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from mpi4py import MPI

R_MM = 10.0
DELTA_MM = 0.1
E_MPA, NU = 1.0, 0.3
E_STAR = E_MPA / (1.0 - NU**2)
F_HERTZ = 4.0 / 3.0 * E_STAR * np.sqrt(R_MM) * DELTA_MM**1.5  # N, whole sphere
A_HERTZ = np.sqrt(R_MM * DELTA_MM)  # mm
L_MM = 200.0  # block edge
H_MIN, H_MAX, R_FINE, GROW = 0.2, 40.0, 1.2, 0.4
PEN_TOL = 2e-4  # Uzawa tolerance (mm): small against delta (0.2 %)
TAG_CONTACT, TAG_BOTTOM, TAG_X0, TAG_Y0, TAG_SIDES = 1, 2, 3, 4, 5


def _quarter_block(comm):
    """Quarter block [0, L] x [0, L] x [-L, 0] meshed by gmsh on rank 0, refined around the
    origin (the first contact point)."""
    import gmsh
    from dolfinx.io import gmshio

    from handfe.anatomy.meshing import ensure_gmsh, release_gmsh

    if comm.rank == 0:
        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("hertz")
        occ = gmsh.model.occ
        vol = occ.addBox(0, 0, -L_MM, L_MM, L_MM, L_MM)
        occ.synchronize()
        groups: dict[int, list[int]] = {}
        for _, s in gmsh.model.getEntities(2):
            cx, cy, cz = occ.getCenterOfMass(2, s)
            tag = (TAG_CONTACT if abs(cz) < 1e-9 else TAG_BOTTOM if abs(cz + L_MM) < 1e-9
                   else TAG_X0 if abs(cx) < 1e-9 else TAG_Y0 if abs(cy) < 1e-9 else TAG_SIDES)
            groups.setdefault(tag, []).append(s)
        for tag, surfs in groups.items():
            gmsh.model.addPhysicalGroup(2, surfs, tag)
        gmsh.model.addPhysicalGroup(3, [vol], 1)
        fld = gmsh.model.mesh.field
        f = fld.add("MathEval")
        fld.setString(f, "F", f"Min({H_MAX}, {H_MIN} + {GROW}*Max(0, Sqrt(x*x+y*y+z*z) - "
                              f"{R_FINE}))")
        fld.setAsBackgroundMesh(f)
        for k, v in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 0),
                     ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.Algorithm3D", 1),
                     ("General.NumThreads", 1)):
            gmsh.option.setNumber(k, v)
        gmsh.model.mesh.generate(3)
    msh, _, ft = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    if comm.rank == 0:
        release_gmsh(gmsh)
    return msh, ft


def _solve(comm, multiplier_degree: int | None = 1) -> dict[str, float]:
    from handfe.contact import Sphere
    from handfe.contact_problem import RigidContact
    from handfe.materials import NeoHookean
    from handfe.solver import Discretisation, HyperelasticProblem, LoadStepping, solve

    msh, ft = _quarter_block(comm)
    prob = HyperelasticProblem(msh, NeoHookean.from_E_nu(E_MPA, NU), disc=Discretisation("p2"))
    bottom = ft.find(TAG_BOTTOM)
    prob.fix(bottom)
    prob.fix(ft.find(TAG_X0), 0.0, components=(0,))
    prob.fix(ft.find(TAG_Y0), 0.0, components=(1,))
    sphere = Sphere(centre=(0.0, 0.0, R_MM), radius=R_MM)
    contact = RigidContact(prob, sphere, ft, TAG_CONTACT, mu=0.0, penalty_factor=50.0,
                           penetration_tol_mm=PEN_TOL, multiplier_degree=multiplier_degree)

    def set_load(t: float) -> None:
        contact.translation.value = np.array([0.0, 0.0, -t * DELTA_MM])

    res = solve(prob, set_load, augment=contact.augment, on_step=contact.on_step,
                stepping=LoadStepping(initial=0.5, min_step=1.0 / 64))
    m = contact.metrics()
    reaction = prob.reaction(bottom)
    # nodal contact pressure on the contact face (the multiplier's owned nodes: vertices and
    # edge midpoints, it has the displacement's degree), radius from the axis
    Q = contact.lambda_n.function_space
    n_own = Q.dofmap.index_map.size_local
    x = Q.tabulate_dof_coordinates()[:n_own]
    lam = contact.lambda_n.x.array[:n_own]
    on_face = np.flatnonzero(np.isclose(x[:, 2], 0.0))
    r = np.hypot(x[on_face, 0], x[on_face, 1])
    p = lam[on_face]
    r_all = np.concatenate(comm.allgather(r))
    p_all = np.concatenate(comm.allgather(p))
    positive = p_all > 0.0
    r_pos = float(r_all[positive].max())
    sel = positive & (r_all < 0.8 * r_pos)
    A = np.vstack([np.ones(sel.sum()), r_all[sel] ** 2]).T
    c0, c1 = np.linalg.lstsq(A, p_all[sel] ** 2, rcond=None)[0]
    return {"force_reaction_N": 4.0 * abs(float(reaction[2])),
            "force_metrics_N": 4.0 * m.normal_force_N,
            "radius_fit_mm": float(np.sqrt(-c0 / c1)),
            "p0_fit_MPa": float(np.sqrt(c0)),
            "radius_positive_mm": r_pos,
            "max_penetration_mm": m.max_penetration_mm,
            "dofs": float(prob.num_dofs()),
            "newton_iterations": float(res.total_newton_iterations)}


@functools.cache
def _serial(multiplier_degree: int | None = 1) -> dict[str, float]:
    return _solve(MPI.COMM_SELF, multiplier_degree)


@pytest.mark.parametrize("multiplier_degree", [1, None], ids=["p1-multiplier", "p2-multiplier"])
def test_hertz_force_radius_penetration(multiplier_degree):
    """P1 multipliers (RigidContact's default) and the displacement's degree (the fingertip's)."""
    r = _serial(multiplier_degree)
    print("\nHertz:", {k: round(v, 6) for k, v in r.items()},
          f"F_H = {F_HERTZ:.6f} N, a_H = {A_HERTZ:.6f} mm")
    assert r["force_reaction_N"] == pytest.approx(F_HERTZ, rel=0.03)
    assert r["force_metrics_N"] == pytest.approx(F_HERTZ, rel=0.03)
    assert r["radius_fit_mm"] == pytest.approx(A_HERTZ, rel=0.03)
    assert r["radius_positive_mm"] == pytest.approx(A_HERTZ, rel=0.05)
    p0_hertz = 2.0 * E_STAR * A_HERTZ / (np.pi * R_MM)
    assert r["p0_fit_MPa"] == pytest.approx(p0_hertz, rel=0.05)
    assert 0.0 <= r["max_penetration_mm"] <= 0.01


@pytest.mark.mpi
def test_hertz_ranks_agree():
    """The distributed solve (COMM_WORLD) equals the serial one (COMM_SELF). Under plain
    pytest COMM_WORLD has one rank and the serial result is reused."""
    ser = _serial()
    par = ser if MPI.COMM_WORLD.size == 1 else _solve(MPI.COMM_WORLD)
    for k in ("force_reaction_N", "force_metrics_N", "radius_fit_mm", "radius_positive_mm"):
        assert par[k] == pytest.approx(ser[k], rel=1e-6), k
    assert par["max_penetration_mm"] == pytest.approx(ser["max_penetration_mm"], rel=1e-5,
                                                      abs=1e-9)

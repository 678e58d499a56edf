"""FE solves with closed-form answers: a unit cube (1 mm) under homogeneous deformation.

The cube [0,1]^3 has symmetry conditions on x=0, y=0, z=0 and a prescribed normal displacement
on x=1 (and y=1 for equibiaxial; y=1 held for pure shear). The nominal stress P11 is the
consistent reaction on x=1 divided by the reference area (1 mm^2). Used by ``handfe material``
and the tests to check the solver core against :func:`handfe.materials.homogeneous`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from dolfinx import mesh as dmesh
from mpi4py import MPI

from handfe.errors import InputError
from handfe.materials import Material, check_homogeneous_mode
from handfe.solver import Discretisation, HyperelasticProblem, LoadStepping, NewtonOptions, solve


def unit_cube(comm: MPI.Comm, n: int = 1):
    return dmesh.create_unit_cube(comm, n, n, n, dmesh.CellType.tetrahedron)


def _facets(msh, axis: int, value: float) -> np.ndarray:
    fdim = msh.topology.dim - 1
    return dmesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[axis], value))


def cube_stress_curve(material: Material, mode: str, stretches: Sequence[float], *,
                      incompressible: bool = False, disc: Discretisation | None = None,
                      comm: MPI.Comm = MPI.COMM_WORLD, n: int = 1,
                      newton: NewtonOptions | None = None) -> np.ndarray:
    """FE nominal stress P11 (MPa) at each stretch (continuation outward from 1)."""
    check_homogeneous_mode(mode, incompressible)
    lams = np.asarray(stretches, dtype=float)
    if np.any(~np.isfinite(lams)) or np.any(lams <= 0):
        raise InputError(f"stretches must be positive and finite, got {list(lams)}")
    if disc is None:
        disc = Discretisation("taylor-hood" if material.supports_mixed else "p2")
    msh = unit_cube(comm, n)
    prob = HyperelasticProblem(msh, material, disc=disc, incompressible=incompressible)
    for axis in range(3):
        prob.fix(_facets(msh, axis, 0.0), components=(axis,))
    right = _facets(msh, 0, 1.0)
    ux = prob.fix(right, components=(0,))
    uy = None
    if mode == "equibiaxial":
        uy = prob.fix(_facets(msh, 1, 1.0), components=(1,))
    elif mode == "shear":
        prob.fix(_facets(msh, 1, 1.0), components=(1,))
    elif mode == "confined":
        for axis in (1, 2):
            prob.fix(_facets(msh, axis, 1.0), components=(axis,))

    state = {"lam": 1.0}

    def go(target: float) -> None:
        start = state["lam"]

        def set_load(t: float) -> None:
            lam = start + t * (target - start)
            ux.value = lam - 1.0
            if uy is not None:
                uy.value = lam - 1.0

        solve(prob, set_load, newton=newton,
              stepping=LoadStepping(initial=1.0, min_step=1e-3, extrapolate=False))
        state["lam"] = target

    out = np.full(lams.shape, np.nan)
    order = np.argsort(lams)
    for direction in (order[lams[order] >= 1.0], order[lams[order] < 1.0][::-1]):
        prob.w.x.array[:] = 0.0
        state["lam"] = 1.0
        for i in direction:
            if lams[i] != state["lam"]:
                go(float(lams[i]))
            out[i] = prob.reaction(right)[0]
    return out


def cook_membrane(comm: MPI.Comm, n: int, material: Material, disc: Discretisation, *,
                  force_N: float = 0.5, thickness_mm: float = 1.0) -> float:
    """Cook's membrane (48 mm wide tapered panel, left edge 44 mm, right edge 16 mm) in plane
    strain (one element layer, u_z = 0), clamped on the left, a shear force ``force_N`` (+y) on
    the right edge. Returns the mean vertical displacement of the loaded edge (mm)."""
    import ufl
    from dolfinx import fem
    from petsc4py import PETSc

    msh = dmesh.create_box(comm, [np.zeros(3), np.array([1.0, 1.0, thickness_mm])], [n, n, 1],
                           dmesh.CellType.tetrahedron)
    x = msh.geometry.x
    xi, eta = x[:, 0].copy(), x[:, 1].copy()
    x[:, 0] = 48.0 * xi
    x[:, 1] = 44.0 * xi + eta * (44.0 - 28.0 * xi)
    prob = HyperelasticProblem(msh, material, disc=disc)
    fdim = 2
    prob.fix(dmesh.locate_entities_boundary(msh, fdim, lambda p: np.isclose(p[0], 0.0)))
    for z in (0.0, thickness_mm):
        prob.fix(dmesh.locate_entities_boundary(msh, fdim, lambda p, z=z: np.isclose(p[2], z)),
                 components=(2,))
    right = dmesh.locate_entities_boundary(msh, fdim, lambda p: np.isclose(p[0], 48.0))
    tags = dmesh.meshtags(msh, fdim, np.sort(right), np.full(len(right), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags, metadata=prob.ds_metadata)
    area = 16.0 * thickness_mm
    ty = fem.Constant(msh, PETSc.ScalarType(0.0))
    prob.add_residual(-ty * prob.vu[1] * ds(1))

    def set_load(t: float) -> None:
        ty.value = t * force_N / area

    solve(prob, set_load, stepping=LoadStepping(initial=0.5))
    uy = fem.assemble_scalar(prob.form(prob.u[1] * ds(1)))
    return comm.allreduce(uy, op=MPI.SUM) / area

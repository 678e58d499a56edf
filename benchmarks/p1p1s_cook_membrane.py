"""Choice of the stabilisation weight beta of the grasp's ``p1-p1s`` element (docs/grasp.md).

Cook's membrane in plane strain (as :func:`handfe.verification.cook_membrane`), neo-Hookean
E = 1 MPa, nu = 0.499, 0.5 N shear, with the mixed energy of ``handfe.grasp.fe.GraspProblem``:
P1 displacement, continuous P1 pressure, ``-(beta h^2 / (2 mu)) |grad p|^2``. Prints
``beta, n, tip_deflection_mm`` as CSV (Taylor-Hood converges to 8.11 mm, plain P1 locks at
3.16 mm for n = 16; tests/test_locking.py).

    .venv/bin/python benchmarks/p1p1s_cook_membrane.py 0.05,0.1,0.2,0.3,1.0
"""

import sys

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.fem.petsc import NonlinearProblem
from dolfinx.nls.petsc import NewtonSolver
from mpi4py import MPI
from petsc4py import PETSc


def cook(n: int, beta: float, nu: float = 0.499, E: float = 1.0, force: float = 0.5) -> float:
    """Mean vertical deflection (mm) of the loaded edge."""
    comm = MPI.COMM_SELF
    msh = dmesh.create_box(comm, [np.zeros(3), np.ones(3)], [n, n, 1],
                           dmesh.CellType.tetrahedron)
    x = msh.geometry.x
    xi, eta = x[:, 0].copy(), x[:, 1].copy()
    x[:, 0] = 48.0 * xi
    x[:, 1] = 44.0 * xi + eta * (44.0 - 28.0 * xi)
    cell = msh.ufl_cell()
    W = fem.FunctionSpace(msh, ufl.MixedElement([ufl.VectorElement("CG", cell, 1),
                                                 ufl.FiniteElement("CG", cell, 1)]))
    w = fem.Function(W)
    u, p = ufl.split(w)
    v = ufl.TestFunction(W)
    mu = E / (2 * (1 + nu))
    kappa = E / (3 * (1 - 2 * nu))
    F = ufl.Identity(3) + ufl.grad(u)
    J = ufl.det(F)
    h = ufl.CellDiameter(msh)
    psi = mu / 2 * (J ** (-2.0 / 3.0) * ufl.tr(F.T * F) - 3) + p * ufl.ln(J) \
        - p ** 2 / (2 * kappa) - 0.5 * beta * h ** 2 / mu * ufl.inner(ufl.grad(p), ufl.grad(p))
    dx = ufl.dx(metadata={"quadrature_degree": 2})
    fdim = 2
    V, _ = W.sub(0).collapse()
    left = dmesh.locate_entities_boundary(msh, fdim, lambda q: np.isclose(q[0], 0.0))
    bcs = [fem.dirichletbc(fem.Function(V), fem.locate_dofs_topological((W.sub(0), V), fdim,
                                                                         left), W.sub(0))]
    Vz, _ = W.sub(0).sub(2).collapse()
    for z in (0.0, 1.0):
        f = dmesh.locate_entities_boundary(msh, fdim, lambda q, z=z: np.isclose(q[2], z))
        dofs = fem.locate_dofs_topological((W.sub(0).sub(2), Vz), fdim, f)
        bcs.append(fem.dirichletbc(fem.Function(Vz), dofs, W.sub(0).sub(2)))
    right = dmesh.locate_entities_boundary(msh, fdim, lambda q: np.isclose(q[0], 48.0))
    tags = dmesh.meshtags(msh, fdim, np.sort(right), np.full(len(right), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    ty = fem.Constant(msh, PETSc.ScalarType(0.0))
    R = ufl.derivative(psi * dx, w, v) - ty * ufl.split(v)[0][1] * ds(1)
    solver = NewtonSolver(comm, NonlinearProblem(R, w, bcs))
    solver.rtol = solver.atol = 1e-10
    ksp = solver.krylov_solver
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    for t in (0.5, 1.0):
        ty.value = t * force / 16.0
        solver.solve(w)
    return fem.assemble_scalar(fem.form(u[1] * ds(1))) / 16.0


if __name__ == "__main__":
    print("beta,n,tip_deflection_mm")
    for beta in [float(b) for b in (sys.argv[1] if len(sys.argv) > 1 else "0.2").split(",")]:
        for n in (2, 4, 8, 16):
            print(f"{beta},{n},{cook(n, beta):.4f}", flush=True)

"""Finite-element part of the grasp: tissue problem, rigid-bone boundary conditions, contact,
a two-form Newton solver and the bone reactions/torques (with their condensed derivative).

The tissue energy is *one* Ogden expression whose parameters are piecewise-constant (DG0)
fields over the skin and subcutaneous cells, plus a compressible neo-Hookean nail: the big Ogden
kernel is compiled once for every grasp, subject and material perturbation. The contact terms
are a separate form (the obstacle's shape is in its code), so a new object only compiles the
small facet kernel. Residual sign as in :mod:`handfe.solver`: R = internal - external; at a bone
node R is the force the bone exerts on the tissue.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from petsc4py import PETSc

from handfe.errors import InputError
from handfe.materials import BoundMaterial, NeoHookean, Ogden, StVenantKirchhoff
from handfe.solver import MUMPS_OPTIONS, Discretisation, lift_unless_satisfied, mumps_lu_ksp
from handfe.step_guard import InversionGuard

SKIN, SUBCUT, NAIL = 1, 2, 3
# guard_damping: a step the guard cut below DAMPING_CUT of its length raises the shift x10
# (from DAMPING_MIN); a step it left whole lowers it /10 (to 0 below DAMPING_MIN)
DAMPING_CUT, DAMPING_MIN = 0.1, 1e-3
# Brezzi-Pitkaranta weight of the equal-order pressure stabilisation (element "p1-p1s"): chosen on
# Cook's membrane (neo-Hookean, nu = 0.499, n = 2/4/8/16): beta = 0.2 gives 4.59/7.12/8.09/
# 8.18 mm against 8.11 mm converged Taylor-Hood (0.05: 7.84 at n = 16, still locked; 1.0: 10.1,
# overshoots); plain P1 (= p1-p0 on tets) 3.16 mm. docs/grasp.md.
STAB_BETA = 0.2


class P1P1Stabilised:
    """P1 displacement + continuous P1 pressure with Brezzi-Pitkaranta stabilisation: the
    mixed energy gets -(beta h^2 / (2 mu0)) |grad p|^2 (h the cell diameter, mu0 the cell's
    small-strain shear modulus). Locking-free on linear tets at about the P1 cost (one pressure
    dof per vertex instead of one per cell as in p1-p0)."""

    element = "p1-p1s"
    degree = 1
    qdeg = 2
    mixed = True
    pressure_element = ("CG", 1)


def discretisation(element: str):
    return P1P1Stabilised() if element == "p1-p1s" else Discretisation(element)


class GraspProblem:
    """Mixed u-p tissue problem on a :class:`~handfe.anatomy.HandModel` (duck-types the parts of
    :class:`handfe.solver.HyperelasticProblem` that :class:`~handfe.contact_problem.RigidContact`
    uses)."""

    def __init__(self, model, skin: Ogden, subcutaneous: Ogden, *, element: str = "p1-p0",
                 nail_E_MPa: float | None = None, ogden_kernel: str = "numpy"):
        mesh = model.mesh
        self.mesh, self.comm = mesh, mesh.comm
        self.disc = discretisation(element)
        cell = mesh.ufl_cell()
        Ve = ufl.VectorElement("CG", cell, self.disc.degree)
        family, pdeg = self.disc.pressure_element
        self.W = fem.FunctionSpace(mesh, ufl.MixedElement([Ve, ufl.FiniteElement(family, cell,
                                                                                 pdeg)]))
        self.w = fem.Function(self.W, name="state")
        self.v = ufl.TestFunction(self.W)
        self.u, self.p = ufl.split(self.w)
        self.vu = ufl.split(self.v)[0]
        ct = model.cell_tags
        self.dx = ufl.Measure("dx", domain=mesh, subdomain_data=ct,
                              metadata={"quadrature_degree": self.disc.qdeg})
        self.ds_metadata = {"quadrature_degree": self.disc.qdeg}
        self.F = ufl.variable(ufl.Identity(3) + ufl.grad(self.u))
        # Ogden parameters as DG0 fields
        D0v = fem.VectorFunctionSpace(mesh, ("DG", 0), dim=len(skin.mu_MPa))
        D0 = fem.FunctionSpace(mesh, ("DG", 0))
        self.mu = fem.Function(D0v, name="ogden_mu")
        self.alpha = fem.Function(D0v, name="ogden_alpha")
        self.inv_kappa = fem.Function(D0, name="inv_kappa")
        self.mu0 = fem.Function(D0, name="shear_modulus")
        self._cells = {t: ct.indices[ct.values == t] for t in (SKIN, SUBCUT, NAIL)}
        self.skin, self.subcutaneous = skin, subcutaneous
        nail = StVenantKirchhoff.nail()
        E_nail = nail_E_MPa if nail_E_MPa is not None else nail.youngs_modulus_MPa
        self._nail_mu0 = E_nail / (2.0 * 1.3)
        self.set_tissue(skin, subcutaneous)
        c = {"mu": self.mu, "alpha": self.alpha}
        J = ufl.det(self.F)
        self.nail = BoundMaterial(NeoHookean.from_E_nu(E_nail, 0.3), mesh)
        e_nail = self.nail.mixed_energy(self.F, self.p)
        if self.disc.degree == 1:
            # grad u is constant on a linear tet: one point integrates W_dev(F) exactly
            dx1 = ufl.Measure("dx", domain=mesh, subdomain_data=ct,
                              metadata={"quadrature_degree": 1})
            # p G(J) is linear in x (P1 pressure, constant J): one point is exact too; only
            # p^2 needs degree 2 (the volumetric form at 4 points cost as much as the rest)
            vol = self.p * skin.vol_G(J) * dx1((SKIN, SUBCUT)) \
                - 0.5 * self.inv_kappa * self.p ** 2 * self.dx((SKIN, SUBCUT))
            self.energy = skin.w_dev(self.F, c) * dx1((SKIN, SUBCUT)) + vol \
                + e_nail * self.dx(NAIL)
        else:
            e_tissue = skin.w_dev(self.F, c) + self.p * skin.vol_G(J) \
                - 0.5 * self.inv_kappa * self.p ** 2
            self.energy = e_tissue * self.dx((SKIN, SUBCUT)) + e_nail * self.dx(NAIL)
        stab = 0
        if self.disc.element == "p1-p1s":
            h = ufl.CellDiameter(mesh)
            gp = ufl.grad(self.p)
            # a constant integrand on P1 (grad p, h, mu0 per cell): one point is exact.
            # Over the three tags, not dx: FFCx compiles an untagged dx as a kernel of its own
            # that dolfinx runs over every cell, a second pass (and 256 more matrix insertions)
            # per cell that cost as much as all the tagged kernels together (coarse pinch:
            # tissue Jacobian 131 -> 67 ms per rank). Every cell must carry one of the tags.
            n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
            tagged = sum(int(np.count_nonzero(c < n_owned)) for c in self._cells.values())
            untagged = self.comm.allreduce(n_owned - tagged, op=MPI.SUM)
            if untagged:
                raise InputError(f"the hand mesh has {untagged} cell(s) without a skin, "
                                 "subcutaneous or nail tag (1, 2, 3): no material is defined "
                                 "on them")
            stab = -0.5 * STAB_BETA * h * h / self.mu0 * ufl.inner(gp, gp) \
                * dx1((SKIN, SUBCUT, NAIL))
            self.energy += stab
        self.internal_residual = ufl.derivative(self.energy, self.w, self.v)
        self.internal_jacobian = None  # None: the derivative of internal_residual
        self.kernel = None
        if ogden_kernel not in ("numpy", "ufl"):
            raise ValueError(f"ogden_kernel must be 'numpy' or 'ufl', got {ogden_kernel!r}")
        if self.disc.degree == 1 and ogden_kernel == "numpy":
            # the deviatoric Ogden part per cell in NumPy (handfe.ogden_p1: ~5x cheaper than
            # the UFL eigenvalue kernel); the volumetric, nail and stabilisation parts stay UFL
            from handfe.ogden_p1 import OgdenP1Kernel

            du = ufl.TrialFunction(self.W)
            self.kernel = OgdenP1Kernel(mesh, self.u, self.mu, self.alpha, self.vu,
                                        ufl.split(du)[0], dx1((SKIN, SUBCUT)))
            rest = vol + e_nail * self.dx(NAIL) + stab
            r_rest = ufl.derivative(rest, self.w, self.v)
            self.internal_residual = r_rest + self.kernel.residual
            self.internal_jacobian = ufl.derivative(r_rest, self.w, du) + self.kernel.jacobian
        self.extra_residual: list = []
        self.bound = {}  # RigidContact gets E_eff explicitly
        self.bcs: list = []

    def set_tissue(self, skin: Ogden, subcutaneous: Ogden) -> None:
        """Assign the skin and subcutaneous Ogden parameters (same term count; no recompile)."""
        if len(skin.mu_MPa) != len(subcutaneous.mu_MPa) or \
                len(skin.mu_MPa) != self.mu.function_space.num_sub_spaces:
            raise ValueError("skin and subcutaneous Ogden sets need the same number of terms")
        n = len(skin.mu_MPa)
        cell_dof = self.inv_kappa.function_space.dofmap.list.array  # DG0: one dof per cell
        cell_blk = self.mu.function_space.dofmap.list.array
        for tag, mat in ((SKIN, skin), (SUBCUT, subcutaneous), (NAIL, subcutaneous)):
            cells = cell_blk[self._cells[tag]]
            mu = self.mu.x.array.reshape(-1, n)
            al = self.alpha.x.array.reshape(-1, n)
            mu[cells] = mat.mu_MPa
            al[cells] = mat.alpha
            self.inv_kappa.x.array[cell_dof[self._cells[tag]]] = 1.0 / mat.bulk_modulus_MPa
            self.mu0.x.array[cell_dof[self._cells[tag]]] = mat.shear_modulus_MPa
        self.mu0.x.array[cell_dof[self._cells[NAIL]]] = self._nail_mu0  # neo-Hookean nail
        for f in (self.mu, self.alpha, self.inv_kappa, self.mu0):
            f.x.scatter_forward()
        self.skin, self.subcutaneous = skin, subcutaneous
        if getattr(self, "kernel", None) is not None:
            self.kernel.refresh_parameters()

    def update_stabilisation(self, pressure_factor: float = 0.0) -> float:
        """Set the stabilisation's shear modulus of the tissue cells to their incremental one
        at the current state (:meth:`OgdenP1Kernel.shear_modulus`, at least mu0) instead of the
        small-strain mu0. With mu0 (0.6-1.2 kPa for the brief's sets) under pad pressures of
        100-500 kPa the term beta h^2 / mu0 |grad p|^2 lets the tissue lose volume wherever
        the pressure varies: cell J 0.1-0.3 under the pads of the coarse cylinder.

        ``pressure_factor`` c > 0 takes at least c |p| (p the cell's mean pressure, MPa). The
        term relaxes the volume constraint by the order of beta delta_p / mu (delta_p the
        pressure change across a cell); with mu >= c |p| that is of the order of
        (beta / c) delta_p / |p|, however far the pressure has risen above the tissue's shear
        stiffness (not where |p| is small and changes by more than itself across a cell).

        The modulus is lagged (a coefficient, not differentiated): call between solves, and
        re-solve. Returns the largest relative change of a cell's modulus (all ranks)."""
        if self.kernel is None:
            raise ValueError("update_stabilisation needs the NumPy Ogden kernel (P1)")
        cell_dof = self.mu0.function_space.dofmap.list.array
        tissue = np.concatenate([self._cells[SKIN], self._cells[SUBCUT]])
        new = self.kernel.shear_modulus()[tissue]
        if pressure_factor > 0.0:
            # a P1 pressure's cell mean = the mean of its 4 vertex dofs (ghost cells too)
            pdof = self.W.sub(1).dofmap.list.array.reshape(-1, 4)
            p_cell = self.w.x.array[pdof[tissue]].mean(axis=1)
            new = np.maximum(new, pressure_factor * np.abs(p_cell))
        old = self.mu0.x.array[cell_dof[tissue]]
        change = float(np.max(np.abs(new - old) / old, initial=0.0))
        self.mu0.x.array[cell_dof[tissue]] = new
        self.mu0.x.scatter_forward()
        return self.comm.allreduce(change, op=MPI.MAX)

    def tissue_cell_J(self) -> tuple[np.ndarray, np.ndarray]:
        """The owned skin and subcutaneous cells (local indices) and each one's J = det F at
        the current state (exact on P1 tets)."""
        if getattr(self, "_J", None) is None:
            D0 = fem.FunctionSpace(self.mesh, ("DG", 0))
            Jf = ufl.det(ufl.Identity(3) + ufl.grad(self.u))
            tissue_dx = self.dx((SKIN, SUBCUT))
            self._J = (fem.Function(D0), fem.Expression(Jf, D0.element.interpolation_points()),
                       fem.form(1.0 * tissue_dx), fem.form(Jf * tissue_dx))
        Jc, expr, _, _ = self._J
        Jc.interpolate(expr)
        nloc = self.mesh.topology.index_map(3).size_local
        tissue = np.concatenate([self._cells[SKIN], self._cells[SUBCUT]])
        tissue = tissue[tissue < nloc]
        return tissue, Jc.x.array[Jc.function_space.dofmap.list.array[tissue]]

    def tissue_volume(self) -> dict[str, float]:
        """Volume change of the skin and subcutaneous tissue: J = det F of each owned cell (at
        its centre; exact on P1 tets), the smallest and largest J, the share of cells with
        J < 0.9 and the deformed / undeformed tissue volume. Near-incompressible tissue
        (nu 0.499) keeps J ~ 1; cells far from 1 mean the element lets it lose volume
        (p1-p1s stabilised with mu0 under pad pressures: cell J 0.1-0.3 under the pads,
        docs/grasp.md)."""
        _, J = self.tissue_cell_J()
        _, _, f0, f1 = self._J
        comm = self.comm
        n = comm.allreduce(len(J), op=MPI.SUM)
        low = comm.allreduce(int(np.count_nonzero(J < 0.9)), op=MPI.SUM)
        vol0 = comm.allreduce(fem.assemble_scalar(f0), op=MPI.SUM)
        vol = comm.allreduce(fem.assemble_scalar(f1), op=MPI.SUM)
        return {"min_cell_J": comm.allreduce(float(J.min(initial=np.inf)), op=MPI.MIN),
                "max_cell_J": comm.allreduce(float(J.max(initial=-np.inf)), op=MPI.MAX),
                "cells_J_below_0.9": low / max(n, 1),
                "volume_ratio": vol / vol0 if vol0 > 0.0 else float("nan")}

    def update(self, tangent: bool = True) -> None:
        """Refresh state-dependent coefficients (the NumPy Ogden kernel) from :attr:`w`; call
        before assembling the internal residual (``tangent=False`` is enough) or Jacobian."""
        if self.kernel is not None:
            self.kernel.update(tangent)

    def add_residual(self, form) -> None:
        self.extra_residual.append(form)

    def num_dofs(self) -> int:
        im = self.W.dofmap.index_map
        return im.size_global * self.W.dofmap.index_map_bs

    def displacement(self) -> fem.Function:
        return self.w.sub(0).collapse()


class TwoFormNewton:
    """SNES Newton (MUMPS LU, backtracking) on R = R_tissue + R_contact with the two forms
    compiled separately; Dirichlet rows from ``problem.bcs``."""

    _count = 0
    #: after a solve whose steps the inversion guard kept short, "; inversion guard shortened
    #: ..." (a stall at a cell near its J bound, not only at a contact kink; a failed solve's
    #: note also says where the smallest cell was), else ""
    guard_note = ""
    #: names where a cell centre (mm, reference) lies, for the guard's note (collective call);
    #: None: the note gives the coordinates
    locate: Callable[[np.ndarray], str] | None = None
    #: Levenberg-Marquardt damping driven by the guard (workflow key solver.guard_damping):
    #: the Jacobian's displacement diagonal gets + damping_shift x |K_ii|; the shift is set
    #: from each step's guard scale (``_precheck``) and carries over to the next solve; the
    #: Jacobians the SNES asks for only (not :func:`condensed_tangent`'s)
    damping = False
    damping_shift = 0.0
    #: the largest shift used so far (summary.json)
    damping_max = 0.0

    def __init__(self, problem: GraspProblem, *, rtol: float = 1e-8, atol: float = 1e-9,
                 max_it: int = 25, guard_keep: float = 0.0):
        self.problem = problem
        #: shortens Newton steps that would take a cell below guard_keep x its J (0 = off)
        self.guard = InversionGuard(problem.w, mixed=True, keep=guard_keep) \
            if guard_keep > 0.0 else None
        W = problem.W
        du = ufl.TrialFunction(W)
        R1 = problem.internal_residual
        R2 = sum(problem.extra_residual)
        self.L = [fem.form(R1), fem.form(R2)]
        J1 = getattr(problem, "internal_jacobian", None)
        if J1 is None:
            J1 = ufl.derivative(R1, problem.w, du)
        self.a = [fem.form(J1), fem.form(ufl.derivative(R2, problem.w, du))]
        self._update = getattr(problem, "update", lambda tangent=True: None)
        self.b = fem_petsc.create_vector(self.L[0])
        self.A = fem_petsc.create_matrix(self.a[0])
        self.x = self.b.duplicate()
        self._work = self.b.duplicate()
        self.history: list[float] = []
        # backtracking by default; "basic" (full Newton steps) as the fallback where the
        # backtracking stalls at a kink of the contact law (semi-smooth residual)
        self._snes = {ls: self._make_snes(ls, rtol, atol, max_it) for ls in ("bt", "basic")}
        self.atol = atol  # N: absolute tolerance of the residual norm (set_atol changes it)
        self.max_it = max_it  # Newton iterations per solve, either line search
        self.line_search = "bt"
        self.snes = self._snes["bt"]
        self.iterations = 0
        #: a failed solve whose last residual norm is <= this is accepted (0 = never)
        self.stall_atol = 0.0
        self.stalls = 0

    def _make_snes(self, line_search: str, rtol: float, atol: float, max_it: int) -> PETSc.SNES:
        snes = PETSc.SNES().create(self.problem.comm)
        TwoFormNewton._count += 1
        prefix = f"handfe_grasp_{TwoFormNewton._count}_"
        snes.setOptionsPrefix(prefix)
        opts = {"snes_type": "newtonls", "snes_linesearch_type": line_search,
                "ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps",
                **MUMPS_OPTIONS}
        db = PETSc.Options()
        for k, v in opts.items():
            db[prefix + k] = v
        snes.setFunction(self._residual, self.b)
        snes.setJacobian(self._jacobian, self.A)
        snes.setTolerances(rtol=rtol, atol=atol, stol=1e-14, max_it=max_it)
        snes.setFromOptions()
        for k in opts:
            db.delValue(prefix + k)
        snes.setMonitor(lambda _s, _it, norm: self.history.append(float(norm)))
        if self.guard is not None:
            snes.setLineSearchPreCheck(self._precheck)
        return snes

    def _precheck(self, x, y) -> bool:
        """The inversion guard, then the damping's update from the scale it took."""
        changed = self.guard(x, y)
        if self.damping:
            s, lm = self.guard.last_scale, self.damping_shift
            if s < DAMPING_CUT:
                lm = max(DAMPING_MIN, 10.0 * lm)
            elif s >= 1.0:
                lm = 0.1 * lm if lm > DAMPING_MIN else 0.0
            self.damping_shift = lm
            self.damping_max = max(self.damping_max, lm)
        return changed

    def _residual(self, snes, x, b):
        p = self.problem
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(p.w.vector)
        p.w.x.scatter_forward()
        self._update(tangent=False)
        with b.localForm() as bl:
            bl.set(0.0)
        for L in self.L:
            fem_petsc.assemble_vector(b, L)
        lift_unless_satisfied(b, self.a, p.bcs, x, self._work)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, p.bcs, x, -1.0)

    def _jacobian(self, snes, x, A, P):
        p = self.problem
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(p.w.vector)
        p.w.x.scatter_forward()
        self._update()
        A.zeroEntries()
        # the Dirichlet diagonal is *inserted*: contact form first with 0, tissue last with 1
        # (and a flush between the inserted diagonal and the next added values)
        fem_petsc.assemble_matrix(A, self.a[1], bcs=self.problem.bcs, diagonal=0.0)
        A.assemblyBegin(PETSc.Mat.AssemblyType.FLUSH)
        A.assemblyEnd(PETSc.Mat.AssemblyType.FLUSH)
        fem_petsc.assemble_matrix(A, self.a[0], bcs=self.problem.bcs, diagonal=1.0)
        A.assemble()
        # the damping is Newton's (snes given), not the tangent's: the condensed tangent of
        # the torque Newton (snes None) stays the true one
        if snes is not None and self.damping_shift > 0.0:
            d = A.getDiagonal()
            m = self._damped_rows()
            d.array[m] += self.damping_shift * np.abs(d.array[m])
            A.setDiagonal(d)
            d.destroy()

    def _damped_rows(self) -> np.ndarray:
        """Owned displacement rows (local indices of the state vector) off the Dirichlet
        dofs: where :attr:`damping_shift` acts."""
        bcs = tuple(self.problem.bcs)
        if getattr(self, "_damped", (None,))[0] != bcs:
            W = self.problem.W
            n = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
            umap = np.asarray(W.sub(0).collapse()[1])
            mask = np.zeros(n, dtype=bool)
            mask[umap[umap < n]] = True
            for bc in bcs:
                idx = bc.dof_indices()[0]
                mask[idx[idx < n]] = False
            self._damped = (bcs, np.flatnonzero(mask))
        return self._damped[1]

    def set_atol(self, atol: float) -> None:
        """Absolute tolerance (N, residual norm) of the later solves, both line searches."""
        for snes in self._snes.values():
            rtol, _, stol, max_it = snes.getTolerances()
            snes.setTolerances(rtol=rtol, atol=atol, stol=stol, max_it=max_it)
        self.atol = float(atol)

    def solve(self, line_search: str | None = None) -> tuple[bool, int, str]:
        """Newton from the current state with ``line_search`` ("bt" or "basic"; default
        :attr:`line_search`). Returns (converged, iterations, SNES reason)."""
        line_search = line_search or self.line_search
        self.last_line_search = line_search
        self.history.clear()
        p = self.problem
        p.w.vector.copy(self.x)
        snes = self._snes[line_search]
        g = self.guard
        self.guard_note = ""
        if g is not None:
            shortened0 = g.shortened
            g.reset()
        try:
            snes.solve(None, self.x)
        except PETSc.Error as exc:
            return False, snes.getIterationNumber(), f"PETSc error {exc}"
        reason = snes.getConvergedReason()
        its = snes.getIterationNumber()
        self.iterations += its
        ok = reason > 0 and all(np.isfinite(self.history))
        if g is not None and g.shortened > shortened0:
            self.guard_note = (f"; inversion guard shortened {g.shortened - shortened0} of "
                               f"{its} steps, to x{g.smallest:.2g} at least; smallest cell J "
                               f"{g.min_J:.2g}")
        if not ok and self.history and all(np.isfinite(self.history)) \
                and self.history[-1] <= self.stall_atol:
            # a stall at a negligible residual (an active-set flip between two contact
            # states): the state is converged for every output we report
            ok, reason = True, f"stalled at {self.history[-1]:.1e} <= stall_atol"
            self.stalls += 1
        if ok:
            self.x.copy(p.w.vector)
            p.w.x.scatter_forward()
            return ok, its, str(reason)
        if self.guard_note:
            # where the smallest cell is, for failed solves only (a KD-tree over the skin and
            # a collective call: not worth it on every converged solve the guard touched)
            self.guard_note += self._where(g.min_J_centre)
        return ok, its, str(reason) + self.guard_note

    def _where(self, centre: np.ndarray | None) -> str:
        """The note's " (where)" for a cell centre (mm, reference): :attr:`locate`'s words,
        else the coordinates. Collective (every rank calls it with the same centre)."""
        if centre is None:
            return ""
        if self.locate is not None:
            return f" ({self.locate(centre)})"
        return " at ({:.1f}, {:.1f}, {:.1f}) mm".format(*centre)

    def adopt_last_iterate(self) -> bool:
        """After a failed :meth:`solve`: make its last iterate the state if every residual of
        that solve was finite (else leave the state alone). Returns whether it did."""
        if not (self.history and all(np.isfinite(self.history))):
            return False
        p = self.problem
        self.x.copy(p.w.vector)
        p.w.x.scatter_forward()
        return True

    def continue_after_stall(self) -> tuple[bool, int, str] | None:
        """After a failed backtracking :meth:`solve` with finite residuals (a stall at a kink
        of the contact law): full Newton steps from its last iterate. None if that does not
        apply (other line search, NaN residuals); the state is then unchanged."""
        if getattr(self, "last_line_search", None) != "bt" or not self.adopt_last_iterate():
            return None
        return self.solve("basic")

    def full_residual(self) -> PETSc.Vec:
        """R (no boundary conditions) at the current state, ghosts summed."""
        b = self.b.duplicate()
        self._update(tangent=False)
        with b.localForm() as bl:
            bl.set(0.0)
        for L in self.L:
            fem_petsc.assemble_vector(b, L)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return b

    def full_matrix(self) -> PETSc.Mat:
        K = fem_petsc.create_matrix(self.a[0])
        self._update()
        K.zeroEntries()
        for a in self.a:
            fem_petsc.assemble_matrix(K, a)
        K.assemble()
        return K

    def destroy(self) -> None:
        for o in (*self._snes.values(), self.A, self.b, self.x, self._work):
            o.destroy()


class BoneBC:
    """Rigid-bone Dirichlet data: every bone's surface nodes follow its rigid motion, the wrist
    (and partial-hand cut) faces are fixed."""

    def __init__(self, problem: GraspProblem, model, bones: list[str]):
        self.problem = problem
        W = problem.W
        V, _ = W.sub(0).collapse()
        self.V = V
        self.ubc = fem.Function(V, name="bone_displacement")
        ft = model.facet_tags
        fdim = model.mesh.topology.dim - 1
        self.X = V.tabulate_dof_coordinates()
        self.blocks: dict[str, np.ndarray] = {}
        self.wdofs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        n_owned = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
        all_f = []
        for b in bones:
            f = ft.find(model.tags[f"bone_{b}"])
            all_f.append(f)
            self.blocks[b] = fem.locate_dofs_topological(V, fdim, f)
            wd, vd = fem.locate_dofs_topological((W.sub(0), V), fdim, f)
            own = wd < n_owned
            self.wdofs[b] = (wd[own], vd[own] // 3, vd[own] % 3)
        for t in (90, 91):
            all_f.append(ft.find(t))
        facets = np.unique(np.concatenate(all_f)).astype(np.int32)
        self.bc_comp_dofs = []
        self.all_comp_dofs = []
        for i in range(3):
            d = fem.locate_dofs_topological(W.sub(0).sub(i), fdim, facets)
            self.bc_comp_dofs.append(d[d < n_owned])
            a = np.unique(W.sub(0).sub(i).dofmap.list.array)
            self.all_comp_dofs.append(a[a < n_owned])
        dofs = fem.locate_dofs_topological((W.sub(0), V), fdim, facets)
        self.bc_dofs_W = dofs[0]
        self._extension_setup(V, fdim, facets)
        problem.bcs.append(fem.dirichletbc(self.ubc, dofs, W.sub(0)))
        self.bones = bones

    def _extension_setup(self, V, fdim, facets) -> None:
        """Linear-elastic extension operator (nu = 0.3, P1) used as the Newton predictor: a bone
        increment is spread smoothly into the tissue before Newton starts, so that the first
        iterate is not a layer of crushed elements next to the bones."""
        mesh = V.mesh
        _, self.V_to_W = self.problem.W.sub(0).collapse()
        self.V_to_W = np.asarray(self.V_to_W)
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        eps = ufl.sym(ufl.grad(u))
        a = (ufl.inner(2 * eps, ufl.sym(ufl.grad(v))) + 0.75 * ufl.div(u) * ufl.div(v)) * ufl.dx
        self.dg = fem.Function(V)
        self._ext_bc = fem.dirichletbc(self.dg, fem.locate_dofs_topological(V, fdim, facets))
        self._ext_a = fem.form(a)
        self._ext_L = fem.form(ufl.inner(fem.Constant(mesh, PETSc.ScalarType((0.0,) * 3)), v)
                               * ufl.dx)
        A = fem_petsc.assemble_matrix(self._ext_a, bcs=[self._ext_bc])
        A.assemble()
        self._ext_A = A
        self._ext_ksp = mumps_lu_ksp(mesh.comm, A)
        self._ext_b = fem_petsc.create_vector(self._ext_L)
        self._ext_x = fem.Function(V)

    def predict(self, old_bc: np.ndarray) -> None:
        """Add the elastic extension of (current bone displacement - ``old_bc``) to the state."""
        self.dg.x.array[:] = self.ubc.x.array - old_bc
        self.dg.x.scatter_forward()
        b = self._ext_b
        with b.localForm() as bl:
            bl.set(0.0)
        fem_petsc.apply_lifting(b, [self._ext_a], bcs=[[self._ext_bc]])
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, [self._ext_bc])
        self._ext_ksp.solve(b, self._ext_x.vector)
        self._ext_x.x.scatter_forward()
        w = self.problem.w
        n = len(self.V_to_W)
        w.x.array[self.V_to_W] += self._ext_x.x.array[:n]
        w.x.scatter_forward()

    def set(self, motions, blend: float = 1.0, previous=None) -> None:
        """Bone displacements from rigid motions {bone: (R, t)} (optionally blended linearly with
        the ``previous`` motions' displacement, for step cutting)."""
        u = self.ubc.x.array.reshape(-1, 3)
        for b in self.bones:
            blk = self.blocks[b]
            R, t = motions[b]
            new = self.X[blk] @ R.T + t - self.X[blk]
            if previous is not None and blend < 1.0:
                R0, t0 = previous[b]
                old = self.X[blk] @ R0.T + t0 - self.X[blk]
                new = old + blend * (new - old)
            u[blk] = new
        self.ubc.x.scatter_forward()

    def node_data(self, b: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Owned W dofs of bone ``b``, their component and current position (mm)."""
        wd, blk, comp = self.wdofs[b]
        x = self.X[blk] + self.ubc.x.array.reshape(-1, 3)[blk]
        return wd, comp, x


def torques_from(vec_arr: np.ndarray, bc: BoneBC, axes_centres, distal_sets, comm) -> np.ndarray:
    """sum over bone nodes of a . ((x - c) x f e_k) with f = -vec (force the tissue exerts on the
    bone), per joint; reduced over ranks."""
    out = np.zeros(len(axes_centres))
    for i, ((a, c), bones) in enumerate(zip(axes_centres, distal_sets, strict=True)):
        s = 0.0
        for b in bones:
            if b not in bc.wdofs:
                continue
            wd, comp, x = bc.node_data(b)
            lever = np.cross(a, x - c)  # (n, 3)
            s += float(np.sum(-vec_arr[wd] * lever[np.arange(len(wd)), comp]))
        out[i] = s
    return np.array(comm.allreduce(out, op=MPI.SUM))


def condensed_torque_jacobian(solver: TwoFormNewton, bc: BoneBC, axes_centres, distal_sets,
                              comm) -> np.ndarray:
    """d(tissue torque_j)/d(theta_i) (N mm / rad) with the tissue in equilibrium
    (:func:`condensed_tangent` without the object's translation)."""
    return condensed_tangent(solver, bc, axes_centres, distal_sets, comm).torque_theta


@dataclass
class CondensedTangent:
    """The FE tangent condensed onto the joint angles theta (rad) and the object's translation
    t (mm), with the tissue in equilibrium. Torques in N mm, object force (the net force the
    skin exerts on the object) in N. ``response_t``: the linear change of the state (owned
    entries of the (u, p) vector) per unit t_c, the predictor of an object move;
    ``response_theta`` (with ``responses``): the same per radian of each joint angle."""

    torque_theta: np.ndarray                     # (joints, joints)
    torque_t: np.ndarray | None = None           # (joints, 3)
    force_theta: np.ndarray | None = None        # (3, joints)
    force_t: np.ndarray | None = None            # (3, 3)
    response_t: list[np.ndarray] = field(default_factory=list)
    response_theta: list[np.ndarray] = field(default_factory=list)


def condensed_tangent(solver: TwoFormNewton, bc: BoneBC, axes_centres, distal_sets, comm, *,
                      translate: bool = False, responses: bool = False) -> CondensedTangent:
    """d(tissue torque_j)/d(theta_i) (N mm / rad) with the tissue in equilibrium: the bone
    nodes of the bones distal to joint i rotate about its axis (v = a_i x (x - c_i)), the free
    dofs follow (K_ff dz = -K_fb v, solved with the factorised Newton matrix), and the change of
    the bone reactions dR = K (v + dz) is turned into torques; plus the geometric part, the
    change of the levers at fixed reactions (:func:`_lever_jacobian`). Joints form chains:
    joint i is proximal to j when j's distal bones are a strict subset of i's, and then j's axis
    and centre turn with theta_i.

    ``translate``: also the derivatives with respect to the object's translation t and those of
    the object force F = sum of R over all nodes (the tissue's own forces sum to zero, so this
    is the contact force on the object). R(u + c, t + c) = R(u, t) for a uniform shift c (the
    tissue energy depends on grad u, the contact on x - t), so moving the object by dt is
    moving every Dirichlet node by -dt: with w_c the response to a unit shift of all Dirichlet
    nodes along e_c, du/dt_c = 1_c - w_c and dR/dt_c = -K w_c.

    ``responses``: keep the state change per radian of each joint (``response_theta``), the
    tangent predictor of a torque step: the pads' response to a bone move as the current
    contact gives it, where the elastic extension of the bone motion pushes them into the
    object."""
    Jm = _lever_jacobian(solver, bc, axes_centres, distal_sets, comm)
    K = solver.full_matrix()
    A = solver.A
    x = solver.problem.w.vector.copy()
    solver._jacobian(None, x, A, None)  # Dirichlet-reduced tangent at the converged state
    x.destroy()
    ksp = mumps_lu_ksp(comm, A)
    v, y, z, dR = (K.createVecRight() for _ in range(4))
    bcd = bc.bc_dofs_W
    n_owned = v.getLocalSize()
    bcd_own = bcd[bcd < n_owned]
    out = CondensedTangent(Jm)
    nj = len(axes_centres)

    def respond(arr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Dirichlet values ``arr`` (owned, zero off the Dirichlet dofs) -> (state change
        v + dz, torque change, object force change) of the equilibrium that follows them."""
        v.setArray(arr)
        K.mult(v, y)
        y.scale(-1.0)
        ya = y.getArray()
        ya[bcd_own] = 0.0
        y.setArray(ya)
        ksp.solve(y, z)
        za = z.getArray()
        za[bcd_own] = 0.0
        z.setArray(za)
        z.axpy(1.0, v)
        K.mult(z, dR)
        r = dR.getArray()
        f = np.array([r[d].sum() for d in bc.all_comp_dofs])
        return (z.getArray().copy(), torques_from(r, bc, axes_centres, distal_sets, comm),
                np.array(comm.allreduce(f, op=MPI.SUM)))

    if translate:
        out.force_theta = np.zeros((3, nj))
    for i, ((a, c), bones) in enumerate(zip(axes_centres, distal_sets, strict=True)):
        arr = np.zeros(n_owned)
        for b in bones:
            if b not in bc.wdofs:
                continue
            wd, comp, x = bc.node_data(b)
            arr[wd] = np.cross(a, x - c)[np.arange(len(wd)), comp]
        z_i, dtq, df = respond(arr)
        if responses:
            out.response_theta.append(z_i)
        Jm[:, i] += dtq
        if translate:
            out.force_theta[:, i] = df
    if translate:
        out.torque_t = np.zeros((nj, 3))
        out.force_t = np.zeros((3, 3))
        for cpt in range(3):
            arr = np.zeros(n_owned)
            arr[bc.bc_comp_dofs[cpt]] = 1.0
            wc, dtq, df = respond(arr)
            out.torque_t[:, cpt] = -dtq
            out.force_t[:, cpt] = -df
            one = np.zeros(n_owned)
            one[bc.all_comp_dofs[cpt]] = 1.0
            out.response_t.append(one - wc)
    for o in (K, v, y, z, dR, ksp):
        o.destroy()
    return out


def _lever_jacobian(solver: TwoFormNewton, bc: BoneBC, axes_centres, distal_sets,
                    comm) -> np.ndarray:
    """Derivative of the torques sum a_j . ((x - c_j) x f) at *fixed* bone forces f (the
    reactions of the converged state) as the bones turn, N mm / rad:
    * i proximal to j: a_j, c_j and the nodes x turn together about a_i, which is the same as
      f turning by -a_i: d = -a_j . ((x - c_j) x (a_i x f)) = f . (a_i x (a_j x (x - c_j)));
    * i = j, or i distal to j (a_j, c_j fixed, the nodes distal to i move by a_i x (x - c_i)):
      d = a_j . ((a_i x (x - c_i)) x f) = f . (a_j x (a_i x (x - c_i))).
    Without it the tangent was 3 % off on the two-joint test chain
    (tests/test_grasp_torque_jacobian.py)."""
    R = solver.full_residual()
    r = R.getArray()
    n = len(axes_centres)
    J = np.zeros((n, n))
    sets = [set(b) for b in distal_sets]
    for j, (aj, cj) in enumerate(axes_centres):
        for i, (ai, ci) in enumerate(axes_centres):
            proximal = i != j and sets[j] < sets[i]
            bones = sets[j] if proximal else sets[i] & sets[j]
            s = 0.0
            for b in bones:
                if b not in bc.wdofs:
                    continue
                wd, comp, x = bc.node_data(b)
                if proximal:
                    g = np.cross(ai, np.cross(aj, x - cj))
                else:
                    g = np.cross(aj, np.cross(ai, x - ci))
                s += float(np.sum(-r[wd] * g[np.arange(len(wd)), comp]))
            J[j, i] = s
    R.destroy()
    return np.array(comm.allreduce(J, op=MPI.SUM))


def global_equilibrium(solver: TwoFormNewton, bc: BoneBC, comm, scale_N: float = 0.0) -> dict:
    """Force on the object (sum of the contact residual, N) against the support reactions
    (sum of the full residual over bone and wrist nodes, N): equal at equilibrium. The error
    is relative to the larger of |object force| and ``scale_N`` (a free object's net force is
    ~0: pass the grip force)."""
    R = solver.full_residual()
    Rc = fem_petsc.assemble_vector(solver.L[1])
    Rc.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    r, rc = R.getArray(), Rc.getArray()
    sup = np.array([r[d].sum() for d in bc.bc_comp_dofs])
    obj = np.array([rc[d].sum() for d in bc.all_comp_dofs])
    sup = np.array(comm.allreduce(sup, op=MPI.SUM))
    obj = np.array(comm.allreduce(obj, op=MPI.SUM))
    R.destroy()
    Rc.destroy()
    err = float(np.linalg.norm(sup - obj) / max(np.linalg.norm(obj), scale_N, 1e-300))
    return {"object_force_N": obj.tolist(), "support_reaction_N": sup.tolist(),
            "equilibrium_relative_error": err}

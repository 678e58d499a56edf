"""Rigid-obstacle contact wired into a :class:`~handfe.solver.HyperelasticProblem`.

:class:`RigidContact` adds the augmented-Lagrangian normal contact (and regularised Coulomb
friction) of :func:`handfe.contact.ufl_contact_terms` on a tagged surface, moves the obstacle
through a ``fem.Constant`` translation (no recompilation between load steps), runs the Uzawa
updates until the largest penetration is below ``penetration_tol_mm`` (0.01 mm by default) and
reports :class:`~handfe.contact.ContactMetrics`. Penalty: scaled automatically from the tissue's
small-strain modulus and the contact facets' size (:func:`handfe.contact.penalty_stiffness`).

Use::

    contact = RigidContact(problem, obstacle, facet_tags, pad_tag, mu=0.74)
    res = solve(problem, set_load, augment=contact.augment, on_step=contact.on_step)
    m = contact.metrics()
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from handfe.contact import (
    ContactMetrics,
    UzawaUpdate,
    contact_metrics,
    friction_anchor_update,
    penalty_stiffness,
    ufl_contact_terms,
)
from handfe.errors import InputError
from handfe.solver import HyperelasticProblem


def facet_size_mm(mesh, facets: np.ndarray) -> float:
    """Mean longest-edge length of ``facets`` (mm), reduced over ranks."""
    fdim = mesh.topology.dim - 1
    comm = mesh.comm
    n_owned = mesh.topology.index_map(fdim).size_local
    f = np.asarray(facets, dtype=np.int32)
    f = f[f < n_owned]
    if len(f):
        from dolfinx.cpp.mesh import entities_to_geometry

        X = mesh.geometry.x[entities_to_geometry(mesh._mesh, fdim, f, False)]  # (n, 3, 3)
        edges = np.linalg.norm(X - np.roll(X, 1, axis=1), axis=2)
        s, n = float(np.sum(edges.max(axis=1))), len(f)
    else:
        s, n = 0.0, 0
    s, n = comm.allreduce(s, op=MPI.SUM), comm.allreduce(n, op=MPI.SUM)
    if n == 0:
        raise InputError("contact surface has no facets")
    return s / n


class RigidContact:
    """Contact between the tagged surface ``tag`` of ``problem``'s mesh and a rigid obstacle.

    ``mu`` friction coefficient (0 = frictionless); ``penalty_factor`` multiplies
    E_tissue / h; ``augmented`` = Uzawa updates until penetration <= ``penetration_tol_mm``;
    ``gap_tol_mm`` defines the contact area in :meth:`metrics`. ``E_eff_MPa`` defaults to the
    smallest small-strain Young's modulus of the problem's materials."""

    def __init__(self, problem: HyperelasticProblem, obstacle: Any, facet_tags, tag: int, *,
                 mu: float = 0.74, penalty_factor: float = 10.0, augmented: bool = True,
                 penetration_tol_mm: float = 0.01, gap_tol_mm: float = 0.01,
                 E_eff_MPa: float | None = None):
        if mu < 0:
            raise InputError(f"friction coefficient mu = {mu} must be >= 0")
        mesh = problem.mesh
        self.problem, self.obstacle, self.facet_tags, self.tag = problem, obstacle, facet_tags, tag
        self.mu, self.gap_tol_mm, self.penetration_tol_mm = mu, gap_tol_mm, penetration_tol_mm
        facets = np.asarray(facet_tags.find(tag), dtype=np.int32)
        self.h_mm = facet_size_mm(mesh, facets)
        if E_eff_MPa is None:
            E_eff_MPa = min(b.material.youngs_modulus_MPa for b in problem.bound.values())
        self.k_n_value = penalty_stiffness(E_eff_MPa, self.h_mm, penalty_factor)
        self.k_n = fem.Constant(mesh, PETSc.ScalarType(self.k_n_value))
        self.translation = fem.Constant(mesh, PETSc.ScalarType((0.0, 0.0, 0.0)))
        self.translation_ref = fem.Constant(mesh, PETSc.ScalarType((0.0, 0.0, 0.0)))
        Q = fem.FunctionSpace(mesh, ("CG", 1))
        self.lambda_n = fem.Function(Q, name="contact_multiplier") if augmented else None
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=facet_tags,
                         metadata=problem.ds_metadata)
        kw: dict[str, Any] = {}
        if mu > 0:
            Vu = fem.VectorFunctionSpace(mesh, ("CG", problem.disc.degree))
            self.u_ref = fem.Function(Vu, name="stick_anchor")
            kw = {"mu": fem.Constant(mesh, PETSc.ScalarType(mu)), "u_ref": self.u_ref,
                  "translation_ref": self.translation_ref}
        else:
            self.u_ref = None
        self.terms = ufl_contact_terms(problem.u, problem.vu, obstacle, self.translation,
                                       ds(tag), k_n=self.k_n, lambda_n=self.lambda_n, **kw)
        problem.add_residual(self.terms.residual)
        self.uzawa = UzawaUpdate(self.terms, facets) if augmented else None
        if mu > 0:
            # nodal slip and pressure at the anchor's dofs, for the return mapping in on_step
            n = self.terms.normal
            Pt = ufl.Identity(3) - ufl.outer(n, n)
            slip = Pt * ((problem.u - self.u_ref) - (self.translation - self.translation_ref))
            pts = Vu.element.interpolation_points()
            self._slip_expr = fem.Expression(slip, pts)
            self._p_expr = fem.Expression(self.terms.pressure, pts)
            self._slip = fem.Function(Vu)
            self._pnode = fem.Function(fem.FunctionSpace(mesh, ("CG", problem.disc.degree)))
        self._u_out: fem.Function | None = None
        self.last_penetration_mm = float("nan")
        self.max_penalty_growth = 64.0

    def augment(self, final: bool = True) -> tuple[bool, float]:
        """Augmented-Lagrangian check after a converged Newton solve.

        The penetration is measured first: if it is within the tolerance (or this is an
        intermediate load step), nothing is changed and the solved state stays consistent with
        its multipliers, so reported forces are the ones the solve balanced. Otherwise one Uzawa
        update (lambda <- p) is made and the solver re-solves. Penalty growth (the standard
        safeguard): when the penetration fell by less than half since the last update, k_n is
        doubled (a Constant: no recompilation), up to ``max_penalty_growth`` x its start value."""
        if self.uzawa is None:
            return True, 0.0
        pen = self.uzawa.penetration()
        if not final or pen <= self.penetration_tol_mm:
            self.last_penetration_mm = pen
            return True, pen
        prev = self.last_penetration_mm
        self.uzawa()
        self.last_penetration_mm = pen
        if math.isfinite(prev) and pen > 0.5 * prev:
            k = float(self.k_n.value)
            if k < self.max_penalty_growth * self.k_n_value:
                self.k_n.value = 2.0 * k
        return False, pen

    def reset_penalty(self) -> None:
        """Back to the automatic penalty (e.g. before a new loading path)."""
        self.k_n.value = self.k_n_value
        self.last_penetration_mm = float("nan")

    def on_step(self, t: float, result: Any) -> None:
        """After an accepted load step: return-map the stick anchor (Coulomb friction with
        memory). Nodes that stuck keep their anchor, so stick persists over load steps; nodes
        that slipped move their anchor to twice the slip limit mu p / k_t; nodes out of
        contact (p = 0) carry no anchor (margin 2: see
        :func:`handfe.contact.friction_anchor_update`). The obstacle's anchor translation stays
        0."""
        if self.u_ref is None:
            return
        self._slip.interpolate(self._slip_expr)
        self._pnode.interpolate(self._p_expr)
        s = self._slip.x.array.reshape(-1, 3)
        shift = friction_anchor_update(s, self._pnode.x.array, self.mu, float(self.k_n.value),
                                       margin=2.0)
        self.u_ref.x.array[:] += shift.reshape(-1)
        self.u_ref.x.scatter_forward()

    def metrics(self, axes=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))) -> ContactMetrics:
        """Contact outputs of the surface (forces N, area mm^2, pressures kPa)."""
        return contact_metrics(self.problem.displacement(), self.obstacle,
                               self.translation.value, self.facet_tags, self.tag,
                               gap_tol_mm=self.gap_tol_mm, pressure=self.terms.pressure,
                               tangential_traction=self.terms.tangential_traction, axes=axes,
                               comm=self.problem.comm)

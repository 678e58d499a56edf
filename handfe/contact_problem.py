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


# Vertex (nodal) quadrature of the contact facets, a custom rule (ffcx 0.5's own "vertex"
# scheme takes the cell's vertices, not the facet's): the contact force is then collocated at
# the nodes, where the Uzawa update enforces the gap. With Gauss points a rigid curved object
# penetrates a flat facet's interior by its sagitta (~0.07 mm for 3.5 mm facets on a 22 mm
# ball) while the nodes are within the tolerance, and k_n x sagitta becomes a force that grows
# with every penalty increase (the coarse pinch: 4.3 N on the thumb pad by the residual, 0.2 N
# by the nodal pressures).
VERTEX_RULE = {"quadrature_rule": "custom", "quadrature_degree": 1,
               "quadrature_points": ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0)),
               "quadrature_weights": (1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0)}


class RigidContact:
    """Contact between the tagged surface ``tag`` of ``problem``'s mesh and a rigid obstacle.

    ``mu`` friction coefficient (0 = frictionless); ``penalty_factor`` multiplies
    E_tissue / h; ``augmented`` = Uzawa updates until penetration <= ``penetration_tol_mm``;
    ``gap_tol_mm`` defines the contact area in :meth:`metrics`. ``E_eff_MPa`` defaults to the
    smallest small-strain Young's modulus of the problem's materials.

    ``augmented_friction`` (with ``augmented`` and mu > 0): tangential Uzawa multipliers carry
    the stick traction, and the updates go on until the stick creep is also below
    ``stick_tol_mm`` (default ``penetration_tol_mm``; see :mod:`handfe.contact`). The stick
    spring is then ``stick_ratio`` x k_n: a softer spring keeps Newton smooth where nodes
    switch between stick and slip, and the multipliers make stick exact anyway. Otherwise the
    stick spring k_t = k_n is the only stick stiffness (creep |t_T| / k_t).

    ``adaptive_penalty`` c (None = off): after each Uzawa update k_n moves towards
    c * p_peak / h (p_peak the largest multiplier, h the facet size), at most doubling per
    update and never falling. For strain-stiffening tissue (the fingertip pulp has almost no
    small-strain stiffness) the E0-based k_n is right at first touch and ~1000x too soft at
    4 N; a penalty that follows the pressure keeps the number of Uzawa updates small.

    ``quadrature``: "gauss" (the problem's facet rule) or "vertex" (nodal collocation of the
    contact force, P1 only; see :data:`VERTEX_RULE`).

    ``friction_smoothing`` delta in [0, 0.5]: the Coulomb cone rounded over (1 +- delta) mu p
    (:func:`handfe.contact.smoothed_cone`; 0 = sharp). Held in the Constant
    ``self.friction_smoothing`` (None if frictionless), which can be changed between solves.

    ``multiplier_degree``: Lagrange degree of the normal multiplier lambda_n, whose nodes are
    where the Uzawa update acts and the penetration is checked (default 1: the vertices);
    None = the displacement's degree (for P2: vertices and edge midpoints, every node at which
    :meth:`metrics` measures the gap; the fingertip scene's choice). P2 multipliers with a
    sliding block (tests/test_friction.py, mu N exceeded) stalled at 94 % of the slide
    (DIVERGED_MAX_IT), so 1 stays the default here."""

    def __init__(self, problem: HyperelasticProblem, obstacle: Any, facet_tags, tag: int, *,
                 mu: float = 0.74, penalty_factor: float = 10.0, augmented: bool = True,
                 penetration_tol_mm: float = 0.01, gap_tol_mm: float = 0.01,
                 E_eff_MPa: float | None = None, augmented_friction: bool = False,
                 adaptive_penalty: float | None = None, stick_ratio: float = 1.0,
                 stick_tol_mm: float | None = None, quadrature: str = "gauss",
                 multiplier_degree: int | None = 1, friction_smoothing: float = 0.0):
        if mu < 0:
            raise InputError(f"friction coefficient mu = {mu} must be >= 0")
        if not 0 <= friction_smoothing <= 0.5:
            raise InputError(f"friction_smoothing = {friction_smoothing!r} must be within "
                             "[0, 0.5]")
        if not 0 < stick_ratio <= 1:
            raise InputError(f"stick_ratio = {stick_ratio!r} must be within (0, 1]")
        if adaptive_penalty is not None and not adaptive_penalty > 0:
            raise InputError(f"adaptive_penalty = {adaptive_penalty!r} must be > 0 (or None)")
        if quadrature not in ("gauss", "vertex"):
            raise InputError(f"contact quadrature = {quadrature!r}: choose 'gauss' or 'vertex'")
        if quadrature == "vertex" and problem.disc.degree != 1:
            raise InputError("vertex contact quadrature needs linear (P1) displacements")
        self.quadrature = quadrature
        mesh = problem.mesh
        self.problem, self.obstacle, self.facet_tags, self.tag = problem, obstacle, facet_tags, tag
        self.mu, self.gap_tol_mm, self.penetration_tol_mm = mu, gap_tol_mm, penetration_tol_mm
        self.adaptive_penalty = adaptive_penalty
        self.stick_tol_mm = penetration_tol_mm if stick_tol_mm is None else stick_tol_mm
        facets = np.asarray(facet_tags.find(tag), dtype=np.int32)
        self.h_mm = facet_size_mm(mesh, facets)
        if E_eff_MPa is None:
            E_eff_MPa = min(b.material.youngs_modulus_MPa for b in problem.bound.values())
        self.k_n_value = penalty_stiffness(E_eff_MPa, self.h_mm, penalty_factor)
        self.k_n = fem.Constant(mesh, PETSc.ScalarType(self.k_n_value))
        self.stick_ratio = stick_ratio
        self._k_t: fem.Constant | None = None
        self.translation = fem.Constant(mesh, PETSc.ScalarType((0.0, 0.0, 0.0)))
        self.translation_ref = fem.Constant(mesh, PETSc.ScalarType((0.0, 0.0, 0.0)))
        qdeg = problem.disc.degree if multiplier_degree is None else int(multiplier_degree)
        if qdeg not in (1, 2):
            raise InputError(f"multiplier_degree = {multiplier_degree!r}: 1, 2 or None")
        Q = fem.FunctionSpace(mesh, ("CG", qdeg))
        self.lambda_n = fem.Function(Q, name="contact_multiplier") if augmented else None
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=facet_tags,
                         metadata=VERTEX_RULE if quadrature == "vertex" else problem.ds_metadata)
        kw: dict[str, Any] = {}
        self.lambda_t: fem.Function | None = None
        if mu > 0:
            Vu = fem.VectorFunctionSpace(mesh, ("CG", problem.disc.degree))
            self.u_ref = fem.Function(Vu, name="stick_anchor")
            self._mu_c = fem.Constant(mesh, PETSc.ScalarType(mu))
            # a Constant, so the cone can be rounded for one solve without recompiling
            self.friction_smoothing = fem.Constant(mesh, PETSc.ScalarType(friction_smoothing))
            kw = {"mu": self._mu_c, "u_ref": self.u_ref,
                  "translation_ref": self.translation_ref,
                  "friction_smoothing": self.friction_smoothing}
            if augmented and augmented_friction:
                self.lambda_t = fem.Function(Vu, name="tangential_multiplier")
                self._k_t = fem.Constant(mesh, PETSc.ScalarType(stick_ratio * self.k_n_value))
                kw.update(lambda_t=self.lambda_t, k_t=self._k_t)
        else:
            self.u_ref = None
            self.friction_smoothing = None
        self.terms = ufl_contact_terms(problem.u, problem.vu, obstacle, self.translation,
                                       ds(tag), k_n=self.k_n, lambda_n=self.lambda_n, **kw)
        problem.add_residual(self.terms.residual)
        self.uzawa = UzawaUpdate(self.terms, facets, ds(tag), self.k_n) if augmented else None
        if mu > 0:
            # nodal slip and pressure at the anchor's dofs, for the return mapping in on_step
            pts = Vu.element.interpolation_points()
            self._slip_expr = fem.Expression(self.terms.slip, pts)
            self._p_expr = fem.Expression(self.terms.pressure, pts)
            self._slip = fem.Function(Vu)
            self._pnode = fem.Function(fem.FunctionSpace(mesh, ("CG", problem.disc.degree)))
            if self.lambda_t is not None:
                self._tT_expr = fem.Expression(self.terms.tangential_traction, pts)
                self._tT = fem.Function(Vu)
                self._t_dofs = fem.locate_dofs_topological(Vu, mesh.topology.dim - 1, facets)
        self._u_out: fem.Function | None = None
        self.last_penetration_mm = float("nan")
        self.last_creep_mm = 0.0
        self.max_penalty_growth = 64.0
        self.history_due = False  # on_step(defer=True) waiting for apply_history()

    @property
    def k_t(self) -> float:
        """Stick spring (MPa/mm): k_n, or stick_ratio * k_n with augmented friction."""
        return float(self.k_n.value if self._k_t is None else self._k_t.value)

    def set_penalty(self, k_n: float) -> None:
        """Set the normal penalty (MPa/mm) and with it the stick spring (Constants: no
        recompilation)."""
        self.k_n.value = float(k_n)
        if self._k_t is not None:
            self._k_t.value = self.stick_ratio * float(k_n)

    def stiffen(self, k_n: float, *, match_forces: bool = True) -> float:
        """Raise the normal penalty to ``k_n`` (MPa/mm; the stick spring follows) keeping the
        contact tractions of the current state: the normal multipliers take up (k_n - k) x
        gap and are then corrected until each node's normal force is what it was
        (:meth:`UzawaUpdate.rescale`: on a curved object a Gauss point is deeper than the
        nodes), and the stick anchors move so that k_t x slip is unchanged (slip x k / k_n).
        What changes is the stiffness of what follows: pressing deeper by dg adds k_n dg
        instead of k dg. Needs the augmented contact; no-op (0) if k_n is not above the
        current penalty. Returns the nodal normal-force mismatch left, relative to the largest
        nodal force (0 with ``match_forces = False``: the nodal pressures only)."""
        if self.uzawa is None:
            raise InputError("stiffen: the contact has no multipliers (augmented = False)")
        k = float(self.k_n.value)
        if not k_n > k:
            return 0.0
        self.apply_history()
        off = self.uzawa.rescale(k, k_n, match_forces=match_forces)
        if self.u_ref is not None:
            self._slip.interpolate(self._slip_expr)
            self.u_ref.x.array[:] += (1.0 - k / k_n) * self._slip.x.array
            self.u_ref.x.scatter_forward()
        self.set_penalty(k_n)
        return off

    def _tangential(self) -> np.ndarray:
        """Nodal tangential traction at the contact dofs, (n, 3), of the current state."""
        self._tT.interpolate(self._tT_expr)
        return self._tT.x.array.reshape(-1, 3)

    def stick_creep(self, tT: np.ndarray | None = None) -> float:
        """Largest |t_T - lambda_t| / k_t over the contact nodes (mm, all ranks): how far the
        augmented stick is from exact stick (0 without augmented friction). ``tT``: the nodal
        tangential traction of the current state if already interpolated."""
        if self.lambda_t is None:
            return 0.0
        d = self._t_dofs
        tT = self._tangential() if tT is None else tT
        diff = tT[d] - self.lambda_t.x.array.reshape(-1, 3)[d]
        # only sticking nodes creep; a slipping node's traction is on the cone (mu p) and
        # changes with p, which the normal updates already converge
        self._pnode.interpolate(self._p_expr)
        p = np.maximum(self._pnode.x.array[d], 0.0)
        stick = np.linalg.norm(tT[d], axis=1) < self.mu * p * (1.0 - 1e-6)
        c = float(np.max(np.linalg.norm(diff[stick], axis=1), initial=0.0)) / self.k_t
        return self.problem.comm.allreduce(c, op=MPI.MAX)

    def _set_lambda_t(self, tT: np.ndarray) -> None:
        lam = np.zeros_like(self.lambda_t.x.array).reshape(-1, 3)
        d = self._t_dofs
        lam[d] = tT[d]
        self.lambda_t.x.array[:] = lam.reshape(-1)
        self.lambda_t.x.scatter_forward()

    def augment(self, final: bool = True, *, tangential: bool = True) -> tuple[bool, float]:
        """Augmented-Lagrangian check after a converged Newton solve.

        The penetration (and, with augmented friction, the stick creep) is measured first: if
        it is within the tolerance (or this is an intermediate load step), nothing is changed
        and the solved state stays consistent with its multipliers, so reported forces are the
        ones the solve balanced. Otherwise one Uzawa update (lambda <- p, lambda_t <- t_T) is
        made and the solver re-solves. ``tangential=False`` leaves lambda_t as it is: right
        after a return mapping of this state (:meth:`on_step`, itself lambda_t <- t_T) a
        second lambda_t <- t_T would give each stuck node its stick correction twice. Penalty
        growth: with ``adaptive_penalty`` see the class docstring; otherwise (the standard
        safeguard) k_n is doubled when the penetration fell by less than half since the last
        update, up to ``max_penalty_growth`` x its start value."""
        if self.uzawa is None:
            return True, 0.0
        pen = self.uzawa.penetration()
        # one interpolation of t_T serves the creep check and the multiplier update
        tT = self._tangential().copy() if self.lambda_t is not None else None
        creep = self.stick_creep(tT)
        if not final or (pen <= self.penetration_tol_mm and creep <= self.stick_tol_mm):
            self.last_penetration_mm, self.last_creep_mm = pen, creep
            return True, max(pen, creep)
        prev = self.last_penetration_mm
        self.uzawa()
        if tT is not None and tangential:
            self._set_lambda_t(tT)
        self.last_penetration_mm, self.last_creep_mm = pen, creep
        k = float(self.k_n.value)
        if self.adaptive_penalty is not None:
            lam = self.lambda_n.x.array
            p_peak = self.problem.comm.allreduce(float(np.max(lam, initial=0.0)), op=MPI.MAX)
            self.set_penalty(min(max(k, self.adaptive_penalty * p_peak / self.h_mm), 2.0 * k))
        elif math.isfinite(prev) and pen > 0.5 * prev:
            if k < self.max_penalty_growth * self.k_n_value:
                self.set_penalty(2.0 * k)
        return False, max(pen, creep)

    def reset_penalty(self) -> None:
        """Back to the automatic penalty (e.g. before a new loading path)."""
        self.set_penalty(self.k_n_value)
        self.last_penetration_mm = float("nan")

    def on_step(self, t: float, result: Any, *, defer: bool = False) -> None:
        """After an accepted load step: the Coulomb return mapping of the stick anchor
        (friction with memory); the obstacle's anchor translation stays 0.

        The mapping changes the stick multipliers and anchors, so the converged state no
        longer balances the contact data until the next solve (a sheared, stuck block: the
        contact's friction force 3 % off the support reaction). ``defer=True`` only marks it
        due; :meth:`apply_history` applies it, called just before the next solve (e.g. in
        the load setter), so a state that is reported balances the data it was solved with.

        Penalty friction: nodes that stuck keep their anchor, so stick persists over load
        steps; nodes that slipped move their anchor to twice the slip limit mu p / k_t; nodes
        out of contact (p = 0) carry no anchor (margin 2: see
        :func:`handfe.contact.friction_anchor_update`). Augmented friction: lambda_t <- t_T;
        nodes that slip (|t_T| = mu p) or are out of contact move their anchor onto the
        current position (the multiplier keeps their traction), stuck nodes keep it."""
        if self.u_ref is None:
            return
        if defer:
            self.history_due = True
            return
        self.history_due = False
        self._slip.interpolate(self._slip_expr)
        self._pnode.interpolate(self._p_expr)
        s = self._slip.x.array.reshape(-1, 3)
        p = np.maximum(self._pnode.x.array, 0.0)
        if self.lambda_t is not None:
            tT = self._tangential().copy()
            self._set_lambda_t(tT)
            slipping = np.linalg.norm(tT, axis=1) >= self.mu * p * (1.0 - 1e-9)
            shift = np.where(slipping[:, None], s, 0.0)
        else:
            shift = friction_anchor_update(s, p, self.mu, self.k_t, margin=2.0)
        self.u_ref.x.array[:] += shift.reshape(-1)
        self.u_ref.x.scatter_forward()

    def set_friction(self, mu: float) -> None:
        """Change the friction coefficient of a contact built with mu > 0 (a Constant: no
        recompilation); 0 makes it frictionless until the next call."""
        if self.u_ref is None:
            raise InputError("set_friction: the contact was built frictionless (mu = 0)")
        if not (math.isfinite(mu) and mu >= 0):
            raise InputError(f"friction coefficient mu = {mu} must be >= 0")
        self.mu = float(mu)
        self._mu_c.value = float(mu)

    def release_stick(self) -> None:
        """Zero tangential traction at the current state: every stick anchor moves onto its
        node's current position (by its slip) and the tangential multipliers are 0."""
        if self.u_ref is None:
            return
        self.history_due = False
        self._slip.interpolate(self._slip_expr)
        self.u_ref.x.array[:] += self._slip.x.array
        self.u_ref.x.scatter_forward()
        if self.lambda_t is not None:
            self.lambda_t.x.array[:] = 0.0

    def apply_history(self) -> None:
        """The return mapping :meth:`on_step` deferred, if it is still due."""
        if self.history_due:
            self.on_step(1.0, None)

    def metrics(self, axes=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
                symmetry_normal=None, area: str = "nodal") -> ContactMetrics:
        """Contact outputs of the surface (forces N, area mm^2, pressures kPa); for a half
        model (``symmetry_normal``) those of the whole body; ``area`` = nodal | clip
        (:func:`contact_metrics`)."""
        return contact_metrics(self.problem.displacement(), self.obstacle,
                               self.translation.value, self.facet_tags, self.tag,
                               gap_tol_mm=self.gap_tol_mm, pressure=self.terms.pressure,
                               tangential_traction=self.terms.tangential_traction, axes=axes,
                               comm=self.problem.comm, symmetry_normal=symmetry_normal,
                               area=area,
                               metadata=VERTEX_RULE if self.quadrature == "vertex" else None)

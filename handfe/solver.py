"""Static large-deformation equilibrium of hyperelastic tissue (units: mm, N, MPa).

* :class:`HyperelasticProblem` builds the weak form on a dolfinx mesh. Near-incompressible tissue
  uses the mixed displacement-pressure ("hybrid") form with Taylor-Hood P2-P1 elements, which
  does not lock (see ``tests/test_locking.py``); ``p2``/``p1`` displacement elements are kept for
  comparison and for laws without a volumetric split.
* :func:`solve` drives the load factor t from 0 to 1 with automatic step cutting on Newton
  failure and step growth after easy steps. Each step is a PETSc SNES ``newtonls`` solve with a
  backtracking line search, MUMPS LU by default; any PETSc option can be passed through (e.g. an
  iterative solver for large meshes). An optional ``augment`` callback runs Uzawa updates
  (augmented-Lagrangian contact) after each converged Newton solve.
* The result is a :class:`SolveResult`; if a step cannot converge after the allowed cuts a
  :class:`~handfe.errors.SolverError` names the load step, the load factor and the last residual.
  Per-step callbacks (``on_step``) run after every accepted step, so whatever they wrote stays.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from petsc4py import PETSc

from handfe.errors import InputError, SolverError
from handfe.materials import BoundMaterial, Material
from handfe.step_guard import InversionGuard

ELEMENTS = ("taylor-hood", "p2", "p1", "p1-p0")
MIXED_ELEMENTS = ("taylor-hood", "p1-p0")
#: the MUMPS options of every Newton LU (ICNTL(14): +200 % workspace over the analysis's
#: estimate, so a factorisation does not fail for lack of it)
MUMPS_OPTIONS = {"mat_mumps_icntl_14": 200}
#: forms on meshes of at most this many cells (the verification cubes) are compiled at gcc -O0:
#: an Ogden Jacobian kernel (3-6 MB of C) takes minutes at the default -O2 and seconds at -O0,
#: and assembles several times slower, which a few cells do not notice (docs/materials.md)
FAST_COMPILE_MAX_CELLS = 200
FAST_COMPILE = {"cffi_extra_compile_args": ["-O0", "-g0"]}
_prefix_counter = itertools.count()


@dataclass(frozen=True)
class Discretisation:
    """Element choice and quadrature degree.

    ``taylor-hood``: P2 displacement + P1 pressure (default; locking-free for nu -> 0.5);
    ``p1-p0``: P1 displacement + piecewise-constant (DG0) pressure in the same mixed u-p form,
    the hybrid linear tetrahedron of the reference model (Abaqus C3D4H-like). Cheap, exact for
    homogeneous states and usable with ``incompressible=True``; but on tetrahedra det F of a P1
    field is constant per cell, so for a finite bulk modulus it gives the same displacements
    as ``p1`` and locks just as much (Cook's membrane, nu = 0.499, n = 4/8/16: 2.63/2.77/3.16
    mm, the p1 numbers, vs 8.11 converged). Use it where bending of near-incompressible tissue
    does not dominate, and check against taylor-hood;
    ``p2`` / ``p1``: displacement only. The quadrature degree must be set by hand: UFL's estimate
    for Ogden forms is ~190 and makes assembly many times slower than the linear solve. Default 4
    for quadratic displacement, 2 for linear (verified by the convergence tests)."""

    element: str = "taylor-hood"
    quadrature_degree: int | None = None

    def __post_init__(self) -> None:
        if self.element not in ELEMENTS:
            raise InputError(f"unknown element '{self.element}' (choose from "
                             f"{', '.join(ELEMENTS)})")
        if self.quadrature_degree is not None and not 1 <= self.quadrature_degree <= 12:
            raise InputError(f"quadrature_degree = {self.quadrature_degree} must be in 1..12")

    @property
    def mixed(self) -> bool:
        return self.element in MIXED_ELEMENTS

    @property
    def degree(self) -> int:
        """Polynomial degree of the displacement."""
        return 1 if self.element in ("p1", "p1-p0") else 2

    @property
    def pressure_element(self) -> tuple[str, int] | None:
        """(family, degree) of the pressure of a mixed element, None otherwise."""
        return {"taylor-hood": ("CG", 1), "p1-p0": ("DG", 0)}.get(self.element)

    @property
    def qdeg(self) -> int:
        return self.quadrature_degree or (4 if self.degree == 2 else 2)


class VectorConstant:
    """Three scalar ``fem.Constant`` set together (``.value = (x, y, z)``), usable as UFL via
    :attr:`ufl`."""

    def __init__(self, mesh, value=(0.0, 0.0, 0.0)):
        self.components = [fem.Constant(mesh, PETSc.ScalarType(0.0)) for _ in range(3)]
        self.value = value

    @property
    def value(self) -> np.ndarray:
        return np.array([float(c.value) for c in self.components])

    @value.setter
    def value(self, v) -> None:
        v = np.asarray(v, dtype=float).reshape(3)
        for c, x in zip(self.components, v, strict=True):
            c.value = x

    @property
    def ufl(self):
        return ufl.as_vector(self.components)


class HyperelasticProblem:
    """Weak form of hyperelastic equilibrium on ``mesh``.

    ``material`` is one :class:`~handfe.materials.Material` for the whole mesh or a mapping from
    cell tag to material (with ``cell_tags``). Parameters are bound as ``fem.Constant`` (see
    :meth:`assign_material`) so changing them does not recompile. Extra residual terms (tractions,
    contact) are added with :meth:`add_residual` before the first solve; Dirichlet conditions
    with :meth:`fix`. Residual sign: R(u; v) = int P : grad v dX - external work = 0.
    ``jit_params`` go to ``fem.form``; by default :data:`FAST_COMPILE` on meshes of at most
    :data:`FAST_COMPILE_MAX_CELLS` cells, dolfinx's defaults otherwise.
    """

    def __init__(self, mesh, material: Material | Mapping[int, Material], *, cell_tags=None,
                 disc: Discretisation | None = None, incompressible: bool = False,
                 jit_params: Mapping[str, Any] | None = None):
        self.mesh = mesh
        self.comm: MPI.Comm = mesh.comm
        if jit_params is None:
            small = mesh.topology.index_map(mesh.topology.dim).size_global \
                <= FAST_COMPILE_MAX_CELLS
            jit_params = FAST_COMPILE if small else {}
        self.jit_params = dict(jit_params)
        self.disc = disc or Discretisation()
        self.incompressible = incompressible
        if incompressible and not self.disc.mixed:
            raise InputError("incompressible=True needs a mixed element (taylor-hood or p1-p0)")
        mats = {None: material} if isinstance(material, Material) else dict(material)
        if len(mats) > 1 and cell_tags is None:
            raise InputError("several materials need cell_tags")
        cell = mesh.ufl_cell()
        Ve = ufl.VectorElement("CG", cell, self.disc.degree)
        if self.disc.mixed:
            family, pdeg = self.disc.pressure_element
            Qe = ufl.FiniteElement(family, cell, pdeg)
            self.W = fem.FunctionSpace(mesh, ufl.MixedElement([Ve, Qe]))
        else:
            self.W = fem.FunctionSpace(mesh, Ve)
        self.w = fem.Function(self.W, name="state")
        self.v = ufl.TestFunction(self.W)
        if self.disc.mixed:
            self.u, self.p = ufl.split(self.w)
            self.vu = ufl.split(self.v)[0]
        else:
            self.u, self.p = self.w, None
            self.vu = self.v
        self.dx = ufl.Measure("dx", domain=mesh, subdomain_data=cell_tags,
                              metadata={"quadrature_degree": self.disc.qdeg})
        self.ds_metadata = {"quadrature_degree": self.disc.qdeg}
        self.F = ufl.variable(ufl.Identity(3) + ufl.grad(self.u))
        self.bound: dict[int | None, BoundMaterial] = {}
        energy = 0
        for tag, mat in mats.items():
            bm = BoundMaterial(mat, mesh, incompressible=incompressible)
            self.bound[tag] = bm
            dxt = self.dx if tag is None else self.dx(tag)
            if self.disc.mixed and mat.supports_mixed:
                energy += bm.mixed_energy(self.F, self.p) * dxt
            elif self.disc.mixed:
                # no volumetric split: pressure is not used here, pin it to zero in these cells
                energy += (bm.strain_energy(self.F) - 0.5 * self.p * self.p) * dxt
            else:
                energy += bm.strain_energy(self.F) * dxt
        self.energy = energy
        self.internal_residual = ufl.derivative(energy, self.w, self.v)
        self.extra_residual: list[Any] = []
        self.bcs: list[fem.DirichletBCMetaClass] = []
        self._compiled: tuple | None = None

    # -- set-up ---------------------------------------------------------------------------------
    @property
    def displacement_space(self):
        return self.W.sub(0) if self.disc.mixed else self.W

    def add_residual(self, form) -> None:
        """Add a residual contribution (UFL 1-form in ``self.v``); before the first solve."""
        if self._compiled is not None:
            raise RuntimeError("add_residual after the forms were compiled")
        self.extra_residual.append(form)

    def fix(self, facets: np.ndarray, value=None, components: tuple[int, ...] | None = None):
        """Dirichlet condition on the displacement at ``facets``: all components to ``value``
        (a length-3 sequence or fem.Constant, default 0) or only the listed ``components`` (each
        set to a scalar; ``value`` a scalar or fem.Constant). Returns the :class:`VectorConstant`
        or fem.Constant, which can be changed between load steps without recompiling."""
        fdim = self.mesh.topology.dim - 1
        Vu = self.displacement_space
        if components is None:
            # dolfinx 0.5 accepts no vector Constant on a mixed sub-space: one scalar per component
            vec = value if isinstance(value, VectorConstant) else VectorConstant(
                self.mesh, np.zeros(3) if value is None else value)
            for i in range(3):
                dofs = fem.locate_dofs_topological(Vu.sub(i), fdim, facets)
                self.bcs.append(fem.dirichletbc(vec.components[i], dofs, Vu.sub(i)))
            return vec
        c = value if isinstance(value, fem.Constant) else fem.Constant(
            self.mesh, PETSc.ScalarType(0.0 if value is None else value))
        for i in components:
            dofs = fem.locate_dofs_topological(Vu.sub(i), fdim, facets)
            self.bcs.append(fem.dirichletbc(c, dofs, Vu.sub(i)))
        return c

    def assign_material(self, material: Material, tag: int | None = None) -> None:
        """Change a bound material's parameter values (no recompilation)."""
        self.bound[tag].assign(material)

    # -- forms ----------------------------------------------------------------------------------
    @property
    def residual(self):
        return self.internal_residual + sum(self.extra_residual) if self.extra_residual \
            else self.internal_residual

    def compiled(self):
        """(residual form, Jacobian form), compiled once."""
        if self._compiled is None:
            R = self.residual
            J = ufl.derivative(R, self.w, ufl.TrialFunction(self.W))
            self._compiled = (self.form(R), self.form(J))
        return self._compiled

    def form(self, f) -> fem.FormMetaClass:
        """``fem.form`` of a UFL form of this problem, with its :attr:`jit_params`."""
        return fem.form(f, jit_params=self.jit_params)

    def first_piola(self, tag: int | None = None):
        """Nominal stress tensor P (MPa), UFL, for the material of ``tag``."""
        bm = self.bound[tag]
        if self.disc.mixed and bm.material.supports_mixed:
            return bm.first_piola(self.F, self.p)
        return bm.first_piola(self.F)

    def num_dofs(self) -> int:
        im = self.W.dofmap.index_map
        return im.size_global * self.W.dofmap.index_map_bs

    def displacement(self) -> fem.Function:
        """The displacement as a collapsed Function (mm), for output."""
        if self.disc.mixed:
            return self.w.sub(0).collapse()
        return self.w

    def reaction(self, facets: np.ndarray) -> np.ndarray:
        """Consistent reaction force (N) on the displacement dofs of ``facets``: the sum of the
        internal residual over those dofs (force the support exerts on the body), reduced over
        ranks (owned dofs only)."""
        L = self.form(self.internal_residual)
        b = fem_petsc.assemble_vector(L)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fdim = self.mesh.topology.dim - 1
        Vu = self.displacement_space
        n_owned = self.W.dofmap.index_map.size_local * self.W.dofmap.index_map_bs
        arr = b.getArray(readonly=True)
        out = np.zeros(3)
        for i in range(3):
            dofs = fem.locate_dofs_topological(Vu.sub(i), fdim, facets)
            dofs = dofs[dofs < n_owned]
            out[i] = arr[dofs].sum()
        b.destroy()
        return np.array([self.comm.allreduce(x, op=MPI.SUM) for x in out])


# ------------------------------------------------------------------------------------------------
def resident_memory_mb() -> float:
    """Resident memory of this process (MB; Linux ``/proc/self/status`` VmRSS), to watch
    factorisations for leaks (:func:`mumps_lu_ksp`)."""
    with open("/proc/self/status") as f:
        return int(f.read().split("VmRSS:")[1].split()[0]) / 1024.0


def mumps_lu_ksp(comm: MPI.Comm, A: PETSc.Mat) -> PETSc.KSP:
    """A direct solver (MUMPS LU) for ``A``; destroy it with ``ksp.destroy()``.

    No Python handle of its PC outlives this function: with petsc4py 3.18, a PC obtained by
    ``ksp.getPC()`` and still referenced when the KSP is destroyed is never freed, and with it
    the LU factor (measured: +22 MB per solve on a 40,000-dof Laplacian; ~150 MB per rank per
    torque iteration on the coarse hand, which ran a 2-rank muscles run out of 24 GB after 31
    min; ``tests/test_fe_core.py::test_mumps_lu_ksp_frees_its_factor``)."""
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("mumps")
    del pc  # before anyone can destroy the KSP
    return ksp


def lift_unless_satisfied(b: PETSc.Vec, a_forms: list, bcs: list, x: PETSc.Vec,
                          work: PETSc.Vec) -> bool:
    """``apply_lifting(b, a_forms, bcs, x0=x, scale=-1)`` unless the iterate ``x`` already holds
    every Dirichlet value, where the lifting adds exactly zero but still computes the element
    matrices of every cell touching a constrained dof (measured: ~75 % of a residual
    evaluation of the fingertip). Newton keeps satisfied values exactly (zero residual and
    identity rows there), so only the first iteration after the values change lifts.
    ``work`` is a vector of b's layout. Collective; returns whether it lifted."""
    with work.localForm() as w:
        w.set(0.0)
    fem_petsc.set_bc(work, bcs, x, -1.0)  # x - g on the constrained owned dofs
    if work.norm(PETSc.NormType.NORM_INFINITY) == 0.0:
        return False
    fem_petsc.apply_lifting(b, a_forms, bcs=[bcs] * len(a_forms), x0=[x] * len(a_forms),
                            scale=-1.0)
    return True


@dataclass(frozen=True)
class NewtonOptions:
    """Newton (PETSc SNES) settings. Converged when ||R|| <= max(atol, rtol ||R_0||).
    ``petsc_options`` are passed through (keys without prefix, e.g. {"ksp_type": "gmres",
    "pc_type": "gamg"}) and override the defaults (direct MUMPS LU).

    ``augment_atol`` (with an augmented-Lagrangian ``augment`` in :func:`solve`; None = off):
    Newton solves stop at this looser absolute tolerance while the multipliers are still being
    updated (their state is only the start of the next solve); once ``augment`` accepts, the
    state is converged to ``atol`` and checked again, so the accepted state meets ``atol``. A
    load step that fails this way is tried once more with every solve converged to ``atol``
    (multipliers updated from loose states can stall Newton) before the step is cut.

    ``inversion_guard`` (0 = off, else in (0, 1)): every Newton step is shortened so that no
    cell's J = det F drops below this fraction of its value at the iterate
    (:mod:`handfe.step_guard`); a step that would invert cells otherwise gives a NaN residual."""

    rtol: float = 1e-9
    atol: float = 1e-10
    max_it: int = 25
    linesearch: str = "bt"
    linear_solver: str = "mumps"
    petsc_options: Mapping[str, Any] = field(default_factory=dict)
    augment_atol: float | None = None
    inversion_guard: float = 0.0


@dataclass(frozen=True)
class LoadStepping:
    """Load-factor stepping on [0, 1]: start with ``initial`` (fraction of the full load), halve
    on failure down to ``min_step``, grow by ``grow`` after a step that took <= ``easy_iterations``
    Newton iterations, never above ``max_step``. ``extrapolate``: linear predictor from the last
    two converged states (retried without it on failure)."""

    initial: float = 0.25
    min_step: float = 1.0 / 1024
    max_step: float = 1.0
    grow: float = 1.5
    easy_iterations: int = 6
    extrapolate: bool = True
    max_augment: int = 20

    def __post_init__(self) -> None:
        if not 0 < self.min_step <= self.initial <= self.max_step <= 1.0:
            raise InputError("load stepping needs 0 < min_step <= initial <= max_step <= 1, got "
                             f"{self.min_step}, {self.initial}, {self.max_step}")


@dataclass
class SolveResult:
    """What a solve did. Lists have one entry per accepted load step."""

    converged: bool = False
    load_factors: list[float] = field(default_factory=list)
    newton_iterations: list[int] = field(default_factory=list)
    residual_history: list[list[float]] = field(default_factory=list)
    augment_iterations: list[int] = field(default_factory=list)
    cuts: int = 0
    wall_s: float = 0.0
    dofs: int = 0

    @property
    def load_steps(self) -> int:
        return len(self.load_factors)

    @property
    def total_newton_iterations(self) -> int:
        return int(sum(self.newton_iterations))

    def summary(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("residual_history")
        d["load_steps"] = self.load_steps
        d["total_newton_iterations"] = self.total_newton_iterations
        return d


_REASONS = {v: k for k, v in vars(PETSc.SNES.ConvergedReason).items() if not k.startswith("_")}


class NewtonSolver:
    """A SNES newtonls solver bound to a :class:`HyperelasticProblem`."""

    def __init__(self, problem: HyperelasticProblem, options: NewtonOptions | None = None):
        self.problem = problem
        self.options = opts = options or NewtonOptions()
        L, a = problem.compiled()
        self._L, self._a = L, a
        self.b = fem_petsc.create_vector(L)
        self.A = fem_petsc.create_matrix(a)
        self.x = self.b.duplicate()
        self._work = self.b.duplicate()
        self.snes = PETSc.SNES().create(problem.comm)
        self.prefix = f"handfe_{next(_prefix_counter)}_"
        self.snes.setOptionsPrefix(self.prefix)
        db = PETSc.Options()
        defaults = {"snes_type": "newtonls", "snes_linesearch_type": opts.linesearch,
                    "ksp_type": "preonly", "pc_type": "lu",
                    "pc_factor_mat_solver_type": opts.linear_solver, **MUMPS_OPTIONS}
        defaults.update(opts.petsc_options)
        for k, v in defaults.items():
            db[self.prefix + k] = v
        self.snes.setFunction(self._residual, self.b)
        self.snes.setJacobian(self._jacobian, self.A)
        self.snes.setTolerances(rtol=opts.rtol, atol=opts.atol, stol=1e-14, max_it=opts.max_it)
        self.snes.setFromOptions()
        for k in defaults:
            db.delValue(self.prefix + k)
        self.history: list[float] = []
        self.snes.setMonitor(lambda _s, _it, norm: self.history.append(float(norm)))
        self.guard = None
        if opts.inversion_guard > 0.0:
            self.guard = InversionGuard(problem.w, mixed=problem.disc.mixed,
                                        keep=opts.inversion_guard)
            self.snes.setLineSearchPreCheck(self.guard)

    def set_atol(self, atol: float) -> None:
        """Absolute residual tolerance of the following solves."""
        self.snes.setTolerances(atol=atol)

    def _residual(self, snes, x, b):
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.problem.w.vector)
        self.problem.w.x.scatter_forward()
        with b.localForm() as bl:
            bl.set(0.0)
        fem_petsc.assemble_vector(b, self._L)
        lift_unless_satisfied(b, [self._a], self.problem.bcs, x, self._work)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.problem.bcs, x, -1.0)

    def _jacobian(self, snes, x, A, P):
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self._a, bcs=self.problem.bcs)
        A.assemble()

    def solve(self) -> tuple[bool, int, list[float], str]:
        """Newton from the current state of ``problem.w``. Returns (converged, iterations,
        residual history, reason)."""
        self.history = []
        self.problem.w.vector.copy(self.x)
        try:
            self.snes.solve(None, self.x)
        except PETSc.Error as exc:  # e.g. a factorisation failure
            return False, self.snes.getIterationNumber(), self.history, f"PETSc error {exc}"
        reason = self.snes.getConvergedReason()
        self.x.copy(self.problem.w.vector)
        self.problem.w.x.scatter_forward()
        ok = reason > 0 and all(np.isfinite(self.history))
        return ok, self.snes.getIterationNumber(), list(self.history), _REASONS.get(reason,
                                                                                  str(reason))

    def destroy(self) -> None:
        for obj in (self.snes, self.A, self.b, self.x, self._work):
            obj.destroy()


def solve(problem: HyperelasticProblem, set_load: Callable[[float], None], *,
          newton: NewtonOptions | None = None, stepping: LoadStepping | None = None,
          on_step: Callable[[float, SolveResult], None] | None = None,
          augment: Callable[[bool], tuple[bool, float]] | None = None,
          progress: Callable[[str], None] | None = None) -> SolveResult:
    """Drive the load factor t from 0 to 1.

    ``set_load(t)`` updates the load (fem.Constant values of Dirichlet data, tractions, obstacle
    positions) for factor t. ``augment(final)`` (optional) is called after each converged Newton
    solve, ``final`` True at t = 1; it updates multipliers and returns (done, violation); Newton is
    repeated until done (at most ``stepping.max_augment`` times). ``on_step(t, result)`` runs
    after each accepted step.
    Raises :class:`SolverError` if a step fails after cutting to ``stepping.min_step``.
    """
    stepping = stepping or LoadStepping()
    res = SolveResult(dofs=problem.num_dofs())
    t0 = time.perf_counter()
    solver = NewtonSolver(problem, newton)
    w = problem.w
    prev = w.vector.copy()  # last converged state
    prev2 = None  # the one before, for the predictor
    t, dt, dt_prev = 0.0, stepping.initial, None
    step = 0
    opts = solver.options
    use_loose = augment is not None and opts.augment_atol is not None and \
        opts.augment_atol > opts.atol
    try:
        while t < 1.0 - 1e-12:
            step += 1
            dt = min(dt, 1.0 - t, stepping.max_step)
            cuts_here = 0
            loose_failed = False
            while True:
                t_new = t + dt
                set_load(t_new)
                tried_pred = False
                if stepping.extrapolate and prev2 is not None and dt_prev:
                    # w = prev + dt/dt_prev (prev - prev2)
                    prev.copy(w.vector)
                    w.vector.axpy(dt / dt_prev, prev)
                    w.vector.axpy(-dt / dt_prev, prev2)
                    w.x.scatter_forward()
                    tried_pred = True
                final = t_new >= 1.0 - 1e-12
                loose = use_loose and not loose_failed
                solver.set_atol(opts.augment_atol if loose else opts.atol)
                ok, its, hist, reason = solver.solve()
                if not ok and tried_pred:
                    prev.copy(w.vector)
                    w.x.scatter_forward()
                    ok, its2, hist2, reason = solver.solve()
                    its, hist = its + its2, hist + hist2
                n_aug = 0
                while ok and augment is not None:
                    done, violation = augment(final)
                    if done and loose:
                        # accepted on a loosely converged state: converge it, check again
                        loose = False
                        solver.set_atol(opts.atol)
                        ok, its2, hist2, reason = solver.solve()
                        its, hist = its + its2, hist + hist2
                        if ok:
                            done, violation = augment(final)
                    if done or not ok:
                        break
                    n_aug += 1
                    if n_aug > stepping.max_augment:
                        ok, reason = False, (f"augmented Lagrangian not converged after "
                                             f"{stepping.max_augment} updates (violation "
                                             f"{violation:.3g})")
                        break
                    ok, its2, hist2, reason = solver.solve()
                    its, hist = its + its2, hist + hist2
                if ok:
                    break
                # failure: restore, cut
                prev.copy(w.vector)
                w.x.scatter_forward()
                last = hist[-1] if hist else float("nan")
                if use_loose and not loose_failed:
                    # the multipliers updated from loosely converged states may be what
                    # failed: the same step once more with every solve converged to atol
                    loose_failed = True
                    if progress:
                        progress(f"  step {step}: {reason} (residual {last:.2e}) with loose "
                                 "solves between multiplier updates; retrying with tight ones")
                    continue
                if dt / 2 < stepping.min_step * (1 - 1e-12):
                    set_load(t)
                    raise SolverError(
                        f"load step {step} (load factor {t:.4g} -> {t_new:.4g}) did not converge "
                        f"after {cuts_here} step cuts (smallest step {dt:.3g}): {reason}, last "
                        f"residual {last:.3e}", load_step=step, load_factor=t_new, residual=last)
                dt /= 2
                cuts_here += 1
                res.cuts += 1
                if progress:
                    progress(f"  step {step}: {reason} (residual {last:.2e}); cutting to "
                             f"dt = {dt:.4g}")
            if prev2 is None:
                prev2 = prev.duplicate()
            prev.copy(prev2)
            w.vector.copy(prev)
            dt_prev = dt
            t = t_new
            res.load_factors.append(t)
            res.newton_iterations.append(int(its))
            res.residual_history.append(hist)
            res.augment_iterations.append(n_aug)
            if progress:
                progress(f"  step {step}: t = {t:.4f}, {its} Newton iterations"
                         + (f", {n_aug} Uzawa updates" if augment else "")
                         + f", |R| = {hist[-1] if hist else 0.0:.2e}")
            if on_step:
                on_step(t, res)
            if its <= stepping.easy_iterations and cuts_here == 0:
                dt = min(dt * stepping.grow, stepping.max_step)
        res.converged = True
    finally:
        res.wall_s = time.perf_counter() - t0
        solver.destroy()
        prev.destroy()
        if prev2 is not None:
            prev2.destroy()
    return res

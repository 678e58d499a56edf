"""Fingertip plate compression (brief §3): a rigid plate at angle theta to the finger axis is
pushed against the pad of an index fingertip whose distal phalanx is rigid and held fixed.

Units: mm, N, MPa; pressures reported in kPa. Deflection = plate travel along its normal after
first contact (brief §3). Control: plate travel (``indent_mm``) or plate force (``force_N``,
reached to 0.5 % by secant refinement between converged states).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from handfe.contact import AREA_METHODS
from handfe.errors import InputError, SolverError
from handfe.materials import Material, MooneyRivlin, NeoHookean

FORCE_RTOL = 0.005
TIGHTEN_AT = 0.85  # fraction of the target force where the loose march tolerances end


@dataclass(frozen=True)
class FingertipConfig:
    """Scene settings. ``material`` None = the calibrated default (:func:`default_material`).

    Contact solver: ``adaptive_penalty`` (k_n follows c * p_peak / h, see
    :class:`~handfe.contact_problem.RigidContact`), ``augmented_friction`` with the stick spring
    ``stick_ratio`` x k_n and stick creep <= ``stick_tol_mm``; during the force march the
    multipliers are converged to ``march_tol_factor`` x the tolerances only (the full ones
    from 85 % of the target force on).

    ``newton_augment_atol_N``: Newton solves followed by a multiplier update stop at this
    residual (N) instead of ``newton_atol_N`` (see
    :class:`~handfe.solver.NewtonOptions`); every accepted state meets ``newton_atol_N``.
    Measured (15 deg, 4 N, 2 ranks): h = 1.5 mm (pad 0.9, the default level then) 107 -> 64
    Newton iterations, 150 -> 88 s wall, deflection 3.0402 -> 3.0403 mm, area (clipped rule)
    168.32 -> 168.35 mm^2; h = 1 mm 79 -> 61, 337 -> 229 s (1e-3 N: 60 iterations at 1.5 mm,
    but h = 1 mm stalled); None = off.

    Mesh: ``mesh`` level, or ``h_mm`` (element size away from the pad) and ``h_pad_mm`` (on
    the pad; default 0.6 h_mm or the level's). ``area_method``: contact area rule, ``nodal``
    (default, lumped nodal area) or ``clip`` (:func:`~handfe.contact.contact_metrics`).
    ``multiplier_degree``: of the normal contact multiplier (None = the displacement's: with
    Taylor-Hood the penetration <= ``penetration_tol_mm`` holds at the edge midpoints too;
    with P1 multipliers they sank up to 0.023 mm at h 2.0 / pad 1.0 mm, 4 N).

    ``half_model``: fingertip and plate load are symmetric about the sagittal plane y = 0, so
    only y >= 0 is meshed, with u_y = 0 on that face; every reported number (forces, areas,
    extents, reactions) is the whole fingertip's. The fields written are the half."""

    subject: str = "mean"
    angle_deg: float = 15.0
    mesh: str = "default"
    h_mm: float | None = None
    h_pad_mm: float | None = None
    element: str = "taylor-hood"
    material: Material | None = None
    layered: bool = False
    skin_thickness_mm: float = 1.0
    skin_material: Material | None = None
    friction: float = 0.74
    penalty_factor: float = 10.0
    penalty_stretch: float = 1.0
    adaptive_penalty: float | None = 10.0
    augmented_friction: bool = True
    stick_ratio: float = 0.3
    stick_tol_mm: float = 0.02
    march_tol_factor: float = 5.0
    newton_atol_N: float = 1e-8
    newton_linesearch: str = "basic"
    newton_augment_atol_N: float | None = 1e-4
    gap_tol_mm: float = 0.01
    area_method: str = "nodal"
    multiplier_degree: int | None = None
    penetration_tol_mm: float = 0.01
    nail_E_MPa: float = 170.0
    half_model: bool = True

    def __post_init__(self) -> None:
        if not (0.0 <= self.angle_deg <= 90.0) or not math.isfinite(self.angle_deg):
            raise InputError(f"plate angle {self.angle_deg!r} deg must be within 0..90")
        if self.friction < 0 or not math.isfinite(self.friction):
            raise InputError(f"friction coefficient {self.friction!r} must be >= 0")
        if not 0.0 < self.stick_ratio <= 1.0:
            raise InputError(f"stick_ratio {self.stick_ratio!r} must be within (0, 1]")
        if not self.stick_tol_mm > 0.0:
            raise InputError(f"stick_tol_mm {self.stick_tol_mm!r} must be > 0")
        if not self.march_tol_factor >= 1.0:
            raise InputError(f"march_tol_factor {self.march_tol_factor!r} must be >= 1")
        if self.newton_augment_atol_N is not None and not (
                math.isfinite(self.newton_augment_atol_N) and self.newton_augment_atol_N > 0.0):
            raise InputError(f"newton_augment_atol_N {self.newton_augment_atol_N!r} must be > 0 "
                             "or None")
        if self.area_method not in AREA_METHODS:
            raise InputError(f"area_method {self.area_method!r}: use one of "
                             f"{', '.join(AREA_METHODS)}")
        if self.adaptive_penalty is not None and not self.adaptive_penalty > 0.0:
            raise InputError(f"adaptive_penalty {self.adaptive_penalty!r} must be > 0 or None")


CALIBRATION_FILE = Path(__file__).resolve().parent.parent / "reference" / \
    "fingertip_calibrated_material.json"


def default_material() -> Material:
    """The pulp material fitted by ``handfe calibrate fingertip`` to the 15-degree deflections
    (``reference/fingertip_calibrated_material.json``), or the brief's published
    Mooney-Rivlin-type fit (C01 = 0.59 kPa, C20 = 2.65 kPa, nu = 0.49) if none was stored."""
    if CALIBRATION_FILE.exists():
        data = json.loads(CALIBRATION_FILE.read_text())
        p = data["parameters"]
        if data["law"] == "mooney-rivlin":
            return MooneyRivlin(**p)
        if data["law"] == "neo-hookean":
            return NeoHookean(**p)
    return MooneyRivlin.fingertip_mean()


def contact_modulus_MPa(material: Material, stretch: float = 1.0) -> float:
    """Modulus that scales the contact penalty (MPa): the uniaxial-compression tangent
    dP/dlambda of ``material`` at ``stretch`` (1.0 = the small-strain Young's modulus E0, the
    default), never below E0.

    Measured (coarse mesh, 15 deg, calibrated pulp, 1 rank, load ~4): with the penalty from
    E0 a 2 N force-controlled solve took 216 Newton iterations and 32 Uzawa updates in 10
    displacement segments; with the tangent at stretch 0.7 (~470 E0, k_n 1.7 MPa/mm) the first
    segment alone (0 -> 2.5 mm) needed 5 step cuts, 31 load steps and ~500 Newton iterations:
    the stiff penalty at the front of the soft pad makes Newton chatter on the active set. So
    E0 stays the default; the option is kept for experiments (docs/contact.md)."""
    from handfe.materials import tangent

    E0 = material.youngs_modulus_MPa
    if not 0.3 <= stretch <= 1.0:
        raise InputError(f"penalty_stretch {stretch!r} must be within 0.3..1")
    if stretch >= 1.0:
        return E0
    try:
        Et = tangent(material, "uniaxial", stretch, incompressible=material.supports_mixed)
    except (ValueError, RuntimeError):  # closed form not available: fall back to E0
        return E0
    return max(E0, float(Et)) if math.isfinite(Et) else E0


@dataclass
class FingertipResult:
    """Outputs of one compression (the keys of ``summary.json``)."""

    force_N: float
    deflection_mm: float
    contact_area_mm2: float
    contact_length_mm: float
    contact_width_mm: float
    mean_pressure_kPa: float
    peak_pressure_kPa: float
    max_penetration_mm: float
    tangential_force_N: float
    bone_reaction_N: list[float]
    plate_force_vector_N: list[float]
    load_steps: int
    newton_iterations: int
    uzawa_updates: int
    dofs: int
    cells: int
    wall_s: float
    solve_s: float
    mesh_s: float
    angle_deg: float
    subject: str
    mesh: str
    element: str
    material: dict[str, Any]
    half_model: bool = False
    h_mm: float = float("nan")  # element size away from the pad, mm
    h_pad_mm: float = float("nan")  # element size on the pad, mm
    area_method: str = "nodal"  # contact area rule (handfe.contact module docstring)
    sweep: list[dict[str, float]] = field(default_factory=list)


class FingertipCompression:
    """The scene: mesh, problem, plate contact. Build once, then :meth:`push_to_force` or
    :meth:`push_to_deflection` (repeatable, continuing from the current state)."""

    def __init__(self, cfg: FingertipConfig, *, comm=None,
                 progress: Callable[[str], None] | None = None):
        from mpi4py import MPI

        from handfe import contact as C
        from handfe.contact_problem import RigidContact
        from handfe.fingertip import build_fingertip_mesh, fingertip_geometry
        from handfe.solver import Discretisation, HyperelasticProblem

        self.cfg = cfg
        self.comm = comm or MPI.COMM_WORLD
        self.progress = progress
        t0 = time.perf_counter()
        self.geom = fingertip_geometry(cfg.subject)
        self.fm = build_fingertip_mesh(self.geom, level=cfg.mesh, h_mm=cfg.h_mm,
                                       h_pad_mm=cfg.h_pad_mm,
                                       layered=cfg.layered,
                                       skin_thickness_mm=cfg.skin_thickness_mm,
                                       half=cfg.half_model, comm=self.comm)
        self.mesh_s = time.perf_counter() - t0
        tags = self.fm.tags
        pulp = cfg.material or default_material()
        self.material = pulp
        mats: dict[int, Material] = {}
        if cfg.layered:
            mats[tags["skin"]] = cfg.skin_material or pulp
            mats[tags["subcutaneous"]] = pulp
        else:
            mats[tags["pulp"]] = pulp
        # the nail as a near-linear elastic plate (small strains): neo-Hookean with E, nu = 0.3
        if "nail" in tags and self.fm.cells_per_tag.get("nail", 1) > 0:
            mats[tags["nail"]] = NeoHookean.from_E_nu(cfg.nail_E_MPa, 0.3)
        self.problem = HyperelasticProblem(self.fm.mesh, mats, cell_tags=self.fm.cell_tags,
                                           disc=Discretisation(cfg.element))
        self.bone_facets = self.fm.facet_tags.find(tags["bone"])
        self.problem.fix(self.bone_facets)
        # half model: the whole fingertip's numbers are the half's mirrored (x 2, no y part)
        self.symmetry_normal = (0.0, 1.0, 0.0) if cfg.half_model else None
        if cfg.half_model:
            self.problem.fix(self.fm.facet_tags.find(tags["symmetry"]), components=(1,))
        self.plate = C.plate(cfg.angle_deg)
        self.n_plate = np.array(self.plate.normal, dtype=float)
        self.contact = RigidContact(self.problem, self.plate, self.fm.facet_tags, tags["pad"],
                                    mu=cfg.friction, penalty_factor=cfg.penalty_factor,
                                    penetration_tol_mm=cfg.penetration_tol_mm,
                                    gap_tol_mm=cfg.gap_tol_mm,
                                    E_eff_MPa=contact_modulus_MPa(pulp, cfg.penalty_stretch),
                                    adaptive_penalty=cfg.adaptive_penalty,
                                    augmented_friction=cfg.augmented_friction,
                                    stick_ratio=cfg.stick_ratio,
                                    stick_tol_mm=cfg.stick_tol_mm,
                                    multiplier_degree=cfg.multiplier_degree)
        # first contact: the plate plane through the lowest pad point along n
        self.g0 = self._initial_gap()
        self.deflection = 0.0
        self._set_plate(0.0)
        import ufl

        ds = ufl.Measure("ds", domain=self.fm.mesh, subdomain_data=self.fm.facet_tags,
                         metadata=self.problem.ds_metadata)
        t = self.contact.terms
        self._force_form = self.problem.form(t.pressure * t.area_factor * ds(tags["pad"]))
        self.results: list[Any] = []

    # -- geometry of the plate --------------------------------------------------------------
    def _initial_gap(self) -> float:
        from mpi4py import MPI

        x = self.fm.mesh.geometry.x
        pad = self.fm.facet_tags.find(self.fm.tags["pad"])
        from dolfinx.mesh import compute_incident_entities

        verts = compute_incident_entities(self.fm.mesh, pad, 2, 0)
        from dolfinx.cpp.mesh import entities_to_geometry

        geo = entities_to_geometry(self.fm.mesh._mesh, 0, verts, False).reshape(-1)
        g, _ = self.plate.gap_normal(x[geo]) if len(geo) else (np.array([np.inf]), None)
        gmin = float(np.min(g)) if len(g) else math.inf
        return self.comm.allreduce(gmin, op=MPI.MIN)

    def _set_plate(self, d: float) -> None:
        self.contact.translation.value = self.n_plate * (self.g0 + d)

    def plate_force(self) -> float:
        """Normal force of the plate on the finger (N): int p da over the pad (x 2 for a half
        model)."""
        from dolfinx import fem
        from mpi4py import MPI

        f = self.comm.allreduce(fem.assemble_scalar(self._force_form), op=MPI.SUM)
        return 2.0 * f if self.cfg.half_model else f

    def metrics(self):
        """Contact metrics of the pad (:class:`~handfe.contact.ContactMetrics`), the whole
        fingertip's also for a half model."""
        return self.contact.metrics(axes=self.axes(), symmetry_normal=self.symmetry_normal,
                                    area=self.cfg.area_method)

    def bone_reaction(self) -> np.ndarray:
        """Force of the bone support on the tissue (N), the whole fingertip's."""
        from handfe.contact import mirrored_total

        R = self.problem.reaction(self.bone_facets)
        return R if self.symmetry_normal is None else mirrored_total(R, self.symmetry_normal)

    # -- loading ------------------------------------------------------------------------------
    def _snapshot(self):
        c = self.contact

        def copy(f):
            return None if f is None else f.x.array.copy()

        return (self.problem.w.x.array.copy(), copy(c.lambda_n), self.deflection,
                copy(c.u_ref), c.translation_ref.value.copy(), copy(c.lambda_t))

    def _restore(self, snap) -> None:
        w, lam, d, uref, tref, lam_t = snap
        c = self.contact
        self.problem.w.x.array[:] = w
        for f, a in ((c.lambda_n, lam), (c.u_ref, uref), (c.lambda_t, lam_t)):
            if a is not None:
                f.x.array[:] = a
        c.translation_ref.value = tref
        self.deflection = d
        self._set_plate(d)

    def _segment(self, d_target: float, initial: float = 1.0, on_point=None):
        from handfe.solver import LoadStepping, NewtonOptions, solve

        d0 = self.deflection

        def set_load(t: float) -> None:
            self.contact.apply_history()  # the last accepted step's friction return mapping
            self._set_plate(d0 + t * (d_target - d0))

        def on_step(t: float, r) -> None:
            # deferred to the next set_load: the reported state balances its contact data
            self.contact.on_step(t, r, defer=True)
            self.deflection = d0 + t * (d_target - d0)
            if on_point is not None:
                on_point(self.deflection)

        # atol 1e-8 N: with the near-incompressible pulp (kappa ~ 5e4 mu0) the residual
        # stagnates at round-off ~1e-9 N; the solver's 1e-10 N default then fails converged
        # steps (seen: DIVERGED_MAX_IT at |R| = 1.8e-9 N and a needless step cut). 1e-8 N is
        # 1e-6 of the 0.5 % force tolerance at 2 N.
        # Line search (cfg.newton_linesearch): full Newton steps ("basic") by default. Measured
        # (reduced mesh, 2 ranks, calibrated pulp, plate 0 -> 0.125 mm): the backtracking line
        # search ("bt") crawls in ~5 % residual decrements (20 iterations), the full step
        # converges quadratically in 4. If a segment fails with the full step, it is retried
        # from the last converged state with "bt" (robust, slow).
        def run_solve(ls: str):
            return solve(self.problem, set_load, augment=self.contact.augment, on_step=on_step,
                         newton=NewtonOptions(atol=self.cfg.newton_atol_N, linesearch=ls,
                                              augment_atol=self.cfg.newton_augment_atol_N),
                         stepping=LoadStepping(initial=initial, min_step=1.0 / 256),
                         progress=self.progress)

        try:
            res = run_solve(self.cfg.newton_linesearch)
        except SolverError:
            if self.cfg.newton_linesearch == "bt":
                raise
            if self.progress:
                self.progress("  segment failed with full Newton steps: retrying with bt")
            d0 = self.deflection
            res = run_solve("bt")
        self.results.append(res)
        self.deflection = d_target
        if self.progress:
            c = self.contact
            self.progress(f"plate at {d_target:.4f} mm: force {self.plate_force():.4g} N, "
                          f"penetration {c.last_penetration_mm:.4f} mm, stick creep "
                          f"{c.last_creep_mm:.4f} mm, k_n {float(c.k_n.value):.3g} MPa/mm")
        return res

    def push_to_deflection(self, d_mm: float, *, on_point=None) -> None:
        if not (math.isfinite(d_mm) and d_mm >= 0.0):
            raise InputError(f"indentation {d_mm!r} mm must be >= 0")
        limit = self.geom.DN0_mm if hasattr(self.geom, "DN0_mm") else 6.4
        if d_mm >= 0.95 * limit:
            raise InputError(f"indentation {d_mm:g} mm is beyond what the pulp "
                             f"({limit:g} mm under the bone) can take")
        self._segment(d_mm, initial=0.25, on_point=on_point)

    def push_to_force(self, force_N: float, *, rtol: float = FORCE_RTOL, on_point=None,
                      max_deflection_mm: float | None = None) -> None:
        """Advance the plate until its normal force is ``force_N`` within ``rtol``.

        March (multipliers converged to ``march_tol_factor`` x the tolerances only): the first
        segment goes to a quarter of the pulp thickness (the soft pad carries almost nothing
        before that), then each segment aims at just below the target by a
        secant of log F against deflection (F grows roughly exponentially with indentation for
        the strain-stiffening pulp), so the path stays monotone. If a segment overshoots, the
        plate goes back to the last converged state below the target (a snapshot, multipliers
        included) and regula falsi in log F between the bracketing states finishes it. From the
        first state near the target on, the augmented-Lagrangian loop is converged to the full
        tolerances."""
        if not (math.isfinite(force_N) and force_N > 0.0):
            raise InputError(f"plate force {force_N!r} N must be positive")
        pulp = getattr(self.geom, "DN0_mm", 6.4)
        dmax = max_deflection_mm or 0.9 * pulp
        F = self.plate_force()
        lo = (self.deflection, F, self._snapshot())
        pts = [(self.deflection, F)]
        aim = force_N * (1.0 - 0.4 * rtol)
        c = self.contact
        tols = (c.penetration_tol_mm, c.stick_tol_mm)
        loose = self.cfg.march_tol_factor > 1.0
        if loose:
            c.penetration_tol_mm, c.stick_tol_mm = (self.cfg.march_tol_factor * t for t in tols)
        try:
            while True:
                if loose and F >= TIGHTEN_AT * force_N:
                    # close to the target: converge the multipliers at this plate position to
                    # the full tolerances (the force rises by ~2 %), then go on with them
                    c.penetration_tol_mm, c.stick_tol_mm = tols
                    loose = False
                    self._segment(self.deflection, on_point=on_point)
                    F = self.plate_force()
                    pts[-1] = (self.deflection, F)
                    if F < force_N:
                        lo = (self.deflection, F, self._snapshot())
                if F >= force_N * (1.0 - rtol):
                    break
                pos = [(d, f) for d, f in pts if f > 1e-6 * force_N]
                if len(pos) >= 2 and pos[-1][0] > pos[-2][0]:
                    (d1, f1), (d2, f2) = pos[-2], pos[-1]
                    slope = (math.log(f2) - math.log(f1)) / (d2 - d1)
                    step = (math.log(aim) - math.log(f2)) / max(slope, 1e-6)
                elif pos:
                    step = 0.75
                else:
                    step = max(0.25 * pulp - self.deflection, 0.5)
                step = float(np.clip(step, 0.02, 1.25))
                d_new = min(self.deflection + step, dmax)
                if d_new <= self.deflection + 1e-9:
                    raise InputError(
                        f"a plate force of {force_N:g} N cannot be reached: at "
                        f"{self.deflection:.2f} mm deflection (limit {dmax:.2f} mm, the pulp is "
                        f"{pulp:.2f} mm thick) the force is {F:.3g} N")
                self._segment(d_new, on_point=on_point)
                F = self.plate_force()
                pts.append((d_new, F))
                if F < force_N:
                    lo = (d_new, F, self._snapshot())
        finally:
            c.penetration_tol_mm, c.stick_tol_mm = tols
        hi = (self.deflection, F)
        stalled = 0
        for _ in range(30):
            if abs(F - force_N) <= rtol * force_N:
                return
            d_lo, F_lo, snap = lo
            d_hi, F_hi = hi
            if F_lo > 0:
                d_new = d_lo + (math.log(force_N / F_lo) * (d_hi - d_lo)
                                / math.log(F_hi / F_lo))
            else:
                d_new = d_lo + (force_N - F_lo) * (d_hi - d_lo) / (F_hi - F_lo)
            if stalled >= 2:  # regula falsi keeps one end: bisect instead
                d_new, stalled = 0.5 * (d_lo + d_hi), 0
            d_new = float(np.clip(d_new, d_lo + 0.05 * (d_hi - d_lo),
                                  d_hi - 0.05 * (d_hi - d_lo)))
            self._restore(snap)
            self._segment(d_new, on_point=on_point)
            F = self.plate_force()
            if F < force_N:
                lo = (d_new, F, self._snapshot())
                stalled += 1
            else:
                hi = (d_new, F)
                stalled = 0
        raise SolverError(f"force control did not reach {force_N:g} N within {rtol:.1%} "
                          f"(last {F:.4g} N at {self.deflection:.4f} mm)")

    # -- outputs ------------------------------------------------------------------------------
    def axes(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """In-plate-plane axes: along the finger axis and across it (y)."""
        th = math.radians(self.cfg.angle_deg)
        return (math.cos(th), 0.0, math.sin(th)), (0.0, 1.0, 0.0)

    def result(self, wall_s: float) -> FingertipResult:
        m = self.metrics()
        R = self.bone_reaction()
        its = sum(r.total_newton_iterations for r in self.results)
        steps = sum(r.load_steps for r in self.results)
        ups = sum(sum(r.augment_iterations) for r in self.results)
        solve_s = sum(r.wall_s for r in self.results)
        mat = self.material
        return FingertipResult(
            force_N=self.plate_force(), deflection_mm=self.deflection,
            contact_area_mm2=m.contact_area_mm2, contact_length_mm=m.length_mm,
            contact_width_mm=m.width_mm, mean_pressure_kPa=m.mean_pressure_kPa,
            peak_pressure_kPa=m.peak_pressure_kPa, max_penetration_mm=m.max_penetration_mm,
            tangential_force_N=m.tangential_force_N, bone_reaction_N=[float(x) for x in R],
            plate_force_vector_N=[float(x) for x in m.force_vector_N], load_steps=steps,
            newton_iterations=its, uzawa_updates=ups, dofs=self.problem.num_dofs(),
            cells=self.fm.num_cells, wall_s=wall_s, solve_s=solve_s, mesh_s=self.mesh_s,
            angle_deg=self.cfg.angle_deg, subject=self.cfg.subject,
            mesh=self.cfg.mesh if self.cfg.h_mm is None and self.cfg.h_pad_mm is None
            else f"h={self.fm.h_mm:g},pad={self.fm.h_pad_mm:g}",
            element=self.cfg.element, half_model=self.cfg.half_model,
            h_mm=self.fm.h_mm, h_pad_mm=self.fm.h_pad_mm, area_method=self.cfg.area_method,
            material={"law": mat.law, **{k: (list(v) if isinstance(v, tuple) else v)
                                         for k, v in asdict(mat).items()}})

    def write_fields(self, out: Path) -> None:
        """Displacement and contact pressure (P1, on the mesh) as XDMF for ParaView."""
        from dolfinx import fem
        from dolfinx.io import XDMFFile

        msh = self.fm.mesh
        V1 = fem.VectorFunctionSpace(msh, ("CG", 1))
        u1 = fem.Function(V1, name="displacement_mm")
        u1.interpolate(self.problem.displacement())
        Q1 = fem.FunctionSpace(msh, ("CG", 1))
        p1 = fem.Function(Q1, name="contact_pressure_kPa")
        p1.interpolate(fem.Expression(1e3 * self.contact.terms.pressure,
                                      Q1.element.interpolation_points()))
        with XDMFFile(msh.comm, str(out / "fields.xdmf"), "w") as xf:
            xf.write_mesh(msh)
            xf.write_meshtags(self.fm.facet_tags)
            xf.write_function(u1)
            xf.write_function(p1)
        self._p1, self._u1 = p1, u1

    def pressure_png(self, path: Path) -> None:
        """Off-screen map of the contact pressure on the pad, seen through the plate."""
        from handfe.io import pad_pressure_png

        pad = self.fm.facet_tags.find(self.fm.tags["pad"])
        pad_pressure_png(self.fm.mesh, pad, self._u1, self._p1, self.axes(), path,
                         title=f"fingertip, plate at {self.cfg.angle_deg:g} deg, "
                               f"{self.plate_force():.2f} N",
                         symmetry_normal=self.symmetry_normal)


def run(cfg: FingertipConfig, *, force_N: float | None = None, indent_mm: float | None = None,
        sweep: bool = False, out_dir: Path | None = None, comm=None,
        progress: Callable[[str], None] | None = None) -> FingertipResult:
    """Build the scene, load it, write outputs (rank 0) into ``out_dir``; return the result."""
    from mpi4py import MPI

    comm = comm or MPI.COMM_WORLD
    if (force_N is None) == (indent_mm is None):
        raise InputError("give exactly one of force_N and indent_mm")
    t0 = time.perf_counter()
    scene = FingertipCompression(cfg, comm=comm, progress=progress)
    points: list[dict[str, float]] = []

    def on_point(d: float) -> None:
        if sweep:
            m = scene.metrics()
            points.append({"deflection_mm": d, "force_N": scene.plate_force(),
                           "contact_area_mm2": m.contact_area_mm2,
                           "contact_length_mm": m.length_mm, "contact_width_mm": m.width_mm,
                           "peak_pressure_kPa": m.peak_pressure_kPa})

    if force_N is not None:
        scene.push_to_force(force_N, on_point=on_point)
    else:
        scene.push_to_deflection(indent_mm, on_point=on_point)
    res = scene.result(time.perf_counter() - t0)
    res.sweep = sorted(points, key=lambda p: p["deflection_mm"])
    if out_dir is not None:
        out_dir = Path(out_dir)
        if comm.rank == 0:
            out_dir.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        scene.write_fields(out_dir)
        if comm.rank == 0:
            from handfe.io import write_csv, write_json

            d = asdict(res)
            d.pop("sweep")
            write_json(out_dir / "summary.json", d)
            if sweep:
                write_csv(out_dir / "sweep.csv", res.sweep)
        scene.pressure_png(out_dir / "pressure.png")
    return res

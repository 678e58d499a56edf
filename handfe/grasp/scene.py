"""Grasp scene assembly and the two loading modes.

Stages: posture (glove angles or a pose file) -> muscle forces (EMG) -> posed mesh of the
participating digits -> object placed in the grasp cavity just short of contact -> FE tissue
problem with rigid bones -> loading -> outputs.

* ``loading = "angles"`` (default): each participating digit closes its released flexion
  joints from the pre-closed posture until it presses with ``solver.digit_force_N`` (bone
  motions as boundary conditions), then Uzawa updates remove the penetration.
* ``loading = "muscles"`` (experimental, not converging yet): after that closing, the released
  flexion joints are unknowns; the applied joint torque ramps from the one holding the closed
  posture to the muscle torque, and Newton on the joint angles balances, at each joint, applied
  + ligament torque + the torque of the tissue reactions on the bones distal to it (contact
  reaches the bones through the tissue). The Jacobian of the tissue torque is the FE tangent
  condensed on the bone rotations plus the lever part.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from mpi4py import MPI

from handfe.errors import ConfigError, InputError, SolverError
from handfe.grasp.config import (
    SolverSpec,
    Workflow,
    angles_only_settings,
    load_workflow,
    muscles_only_settings,
)
from handfe.materials import Ogden


@dataclass
class GraspResult:
    regions: dict[str, dict[str, float]]
    summary: dict[str, Any]
    out_dir: Path | None = None
    fingertips: dict[str, dict[str, float]] = field(default_factory=dict)


def make_obstacle(spec, H) -> Any:
    """The object in world coordinates (the hand frame H maps hand -> world)."""
    from handfe.contact import Capsule, Cylinder, RoundedBox, Sphere

    c = H.apply(np.asarray(spec.centre_mm, dtype=float))
    ax = H.R @ np.asarray(spec.axis, dtype=float)
    ax = ax / np.linalg.norm(ax)
    if spec.shape == "sphere":
        return Sphere(centre=tuple(c), radius=spec.radius_mm)
    if spec.shape == "cylinder":
        return Cylinder(centre=tuple(c), axis=tuple(ax), radius=spec.radius_mm,
                        half_length=spec.length_mm / 2,
                        edge_radius=min(spec.edge_radius_mm, spec.radius_mm))
    if spec.shape == "capsule":
        h = spec.length_mm / 2
        return Capsule(a=tuple(c - h * ax), b=tuple(c + h * ax), radius=spec.radius_mm)
    # box: axes = rows of the hand frame rotated so that box x = spec.axis
    e0 = ax
    e1 = np.cross(H.R[:, 2], e0)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e0, e1)
    return RoundedBox(centre=tuple(c), half_sizes=tuple(spec.half_sizes_mm),
                      rotation=tuple(map(tuple, np.stack([e0, e1, e2], axis=1))),
                      edge_radius=spec.edge_radius_mm)


def place_object(obstacle, spec, H, surface, regions: tuple[str, ...], source: str,
                 reach: dict[str, np.ndarray] | None = None, reach_depth_mm: float = 8.0
                 ) -> tuple[
        np.ndarray, float, dict[str, float]]:
    """Snug placement (rank-0 surface data): the shift (world, mm) within the search box that
    makes the *largest* of the per-region smallest gaps as small as possible while every gap
    stays >= ``spec.min_clearance_mm`` (the object sits as close to every participating region
    as the posture allows, touching none). With ``reach`` ({digit: its skin points swept
    through its closing arc}), placements where a digit's arc does not pass at least
    ``reach_depth_mm`` into the object are penalised first (a digit whose arc only grazes the
    object would never press on it).
    Returns (shift, clearance_mm, gap per region at the start posture)."""
    from scipy.optimize import minimize

    from handfe.grasp.outputs import region_of

    tri_reg = np.array([region_of(c)[0] for c in surface.codes])
    pts = {r: surface.points[np.unique(surface.triangles[tri_reg == r])] for r in regions
           if np.any(tri_reg == r)}
    allp = surface.points
    half = np.asarray(spec.search_mm, dtype=float)
    Rh = H.R
    cmin = spec.min_clearance_mm

    def gaps(s_h: np.ndarray) -> np.ndarray:
        s = Rh @ s_h
        return np.array([obstacle.gap_normal(p, s)[0].min() for p in pts.values()])

    reach = {d: p for d, p in (reach or {}).items() if d in pts and len(p)}

    def cost(s_h: np.ndarray) -> float:
        g = gaps(s_h)
        g_all = obstacle.gap_normal(allp, Rh @ s_h)[0].min()
        c = 100.0 * max(0.0, cmin + 0.02 - min(g.min(), g_all))  # margin: the optimum sits on it
        if reach:
            keys = list(pts)
            arc = np.array([obstacle.gap_normal(reach[r], Rh @ s_h)[0].min() if r in reach
                            else g[keys.index(r)] for r in keys])
            return float(c + 10.0 * max(0.0, arc.max() + reach_depth_mm) + g.max())
        return float(g.max() + c)

    axes = [np.linspace(-h, h, 11) if h > 0 else np.zeros(1) for h in half]
    best, best_c = np.zeros(3), np.inf
    for x in axes[0]:
        for y in axes[1]:
            for z in axes[2]:
                c = cost(np.array([x, y, z]))
                if c < best_c:
                    best, best_c = np.array([x, y, z]), c
    free = half > 0
    if free.any():
        def f(q):
            s = best.copy()
            s[free] = np.clip(q, -half[free], half[free])
            return cost(s)
        r = minimize(f, best[free], method="Nelder-Mead",
                     options={"xatol": 0.01, "fatol": 1e-4, "maxiter": 600})
        if r.fun < best_c:
            best[free] = np.clip(r.x, -half[free], half[free])
    g = gaps(best)
    g_all = float(obstacle.gap_normal(allp, Rh @ best)[0].min())
    clearance = min(float(g.min()), g_all)
    if clearance < cmin - 1e-6:
        raise ConfigError(
            f"{source}: 'object' intersects the hand in this posture: best clearance to the skin "
            f"{clearance:.2f} mm (< min_clearance_mm = {cmin}) within search_mm = "
            f"{list(spec.search_mm)} around centre_mm = {list(spec.centre_mm)}; move or shrink "
            "the object, or raise opening_deg")
    return Rh @ best, clearance, {r: float(x) for r, x in zip(pts, g, strict=True)}


def start_gaps(obstacle, shift: np.ndarray, surface) -> dict[str, float]:
    """Smallest skin-object gap (mm) per region (thumb..little, palm) of a skin surface."""
    from handfe.grasp.outputs import region_of

    g = obstacle.gap_normal(surface.points, np.asarray(shift, dtype=float))[0]
    tri_reg = np.array([region_of(c)[0] for c in surface.codes])
    out = {}
    for r in ("thumb", "index", "middle", "ring", "little", "palm"):
        sel = tri_reg == r
        if sel.any():
            out[r] = float(g[np.unique(surface.triangles[sel])].min())
    return out


def palm_direction(obstacle, shift: np.ndarray, surface, digits: tuple[str, ...],
                   thumb_kept: bool = True) -> tuple[np.ndarray, float, float]:
    """Direction (world, unit) in which the object moves into the palm: the digits' push, the
    sum over the participating digits of the object's inward normal at each digit's nearest
    skin point, -sum(n_i), i.e. where equal digit forces along their contact normals would
    push it. (The palm's own normal, tried first, pressed the object into the index's
    proximal phalanx: the coarse cylinder's index took 31 N before it closed; docs/grasp.md.)
    Also the palm's smallest gap (mm) and |sum(n_i)| (the push of the digits per N of digit
    force). Rank-0 surface data."""
    from handfe.grasp.outputs import region_of

    tri_reg = np.array([region_of(c)[0] for c in surface.codes])
    if not (tri_reg == "palm").any():
        raise InputError("the mesh has no palm skin: 'solver.palm_force_N' needs one")
    push = np.zeros(3)
    normal = {}
    for r in digits:
        sel = tri_reg == r
        if sel.any():
            g, n = obstacle.gap_normal(surface.points[np.unique(surface.triangles[sel])],
                                       np.asarray(shift, dtype=float))
            normal[r] = n[int(np.argmin(g))]
            push -= normal[r]
    size = float(np.linalg.norm(push))
    if size < 1e-6:
        raise InputError("the digits' push on the object is 0 (they surround it evenly): "
                         "'solver.palm_force_N' has no direction to move it in")
    d = push / size
    if thumb_kept and "thumb" in normal and d @ normal["thumb"] < 0.0:
        # without the part that leaves the thumb: its closing through the thenar tissue is
        # the one Newton struggles with (coarse cylinder: 4 mm away, 13 deg more closing, one
        # step cut to 1/32 for 700 s)
        d = d - (d @ normal["thumb"]) * normal["thumb"]
        d /= np.linalg.norm(d)
    palm = surface.points[np.unique(surface.triangles[tri_reg == "palm"])]
    gap = float(obstacle.gap_normal(palm, np.asarray(shift, dtype=float))[0].min())
    return d, gap, size


def measured_pose(wf: Workflow, grasp, subject_dir: Path):
    """The grasp's measured posture and where it came from: the subject's glove angles (mean
    of the hold windows) or the grasp's pose TOML."""
    from handfe.kinematics import Pose, grasp_pose
    from handfe.paths import REPO_ROOT

    if grasp.pose == "glove":
        return grasp_pose(subject_dir, grasp.name), "glove (mean of hold windows)"
    p = Path(grasp.pose)
    p = p if p.is_absolute() else REPO_ROOT / p
    return Pose.from_toml(p), str(p)


#: a finished run whose object force and support reactions differ by more than this
#: (relative) ends with status "unbalanced" instead of "done"
EQUILIBRIUM_RTOL = 1e-6


def balance_problems(summary: Mapping[str, Any], mode: str, torque_rtol: float) -> list[str]:
    """Why a finished run's final state is not a balanced one (empty if it is): the object
    force against the support reactions (relative, :data:`EQUILIBRIUM_RTOL`) and, in the
    muscles mode, the largest relative torque residual of a released joint off its limits
    against ``torque_rtol`` (the tight solve of a stalled final state moves the tissue
    torques: 5.2e-4 -> 2.1e-3 on the coarse cylinder, docs/grasp.md twentieth session)."""
    out = []
    eq = summary.get("equilibrium_relative_error")
    if eq is not None and not eq <= EQUILIBRIUM_RTOL:
        out.append(f"object force vs support reactions {eq:.2g} relative, tolerance "
                   f"{EQUILIBRIUM_RTOL:g}")
    tq = summary.get("max_relative_torque_residual")
    if mode == "muscles" and tq is not None and not tq <= torque_rtol:
        out.append(f"relative torque residual {tq:.2g} at a released joint, tolerance "
                   f"{torque_rtol:g} (solver.torque_rtol)")
    return out


@dataclass(frozen=True)
class FullLoadRecipe:
    """The [solver] keys with which the muscle-driven mode has run to the end ('done') at the
    full EMG load on one grasp and mesh level (at least these values; ``workflow`` ships
    them). No keys: any solver settings. ``record``: what its whole runs did, when not every
    one ran to the end (said before a run with these keys too)."""

    workflow: str
    guard_damping: bool = False
    muscle_stall_rtol: float = 0.0
    inversion_guard: float = 0.0
    record: str = ""

    def _needs(self) -> list[tuple[str, float]]:
        """(key, least value) of each [solver] key the recipe needs (a bool as 0 / 1)."""
        return [(k, v) for k, v in (("guard_damping", self.guard_damping),
                                    ("muscle_stall_rtol", self.muscle_stall_rtol),
                                    ("inversion_guard", self.inversion_guard)) if v]

    def keys(self) -> str:
        """The keys in words ("" when none are needed)."""
        return " and ".join("solver.guard_damping = true" if k == "guard_damping"
                            else f"solver.{k} >= {_num(v)}" for k, v in self._needs())

    def met_by(self, solver: SolverSpec | None) -> bool:
        needs = self._needs()
        return not needs or (solver is not None
                             and all(getattr(solver, k) >= v for k, v in needs))


def _num(v: float) -> str:
    """3e-4, not 0.0003; 0.5 as it is."""
    return f"{v:g}" if v >= 0.01 else f"{v:.0e}".replace("e-0", "e-")


#: (grasp, mesh level) -> what ran to the end at the full EMG load there (docs/grasp.md:
#: cylinder coarse, twenty-second session; reduced, thirty-seventh; ball, forty-second)
FULL_LOAD_RECIPES = {
    ("cylindrical", "coarse"): FullLoadRecipe("cylindrical_muscles.toml"),
    ("cylindrical", "reduced"): FullLoadRecipe("cylindrical_muscles_reduced.toml",
                                               guard_damping=True, muscle_stall_rtol=3e-4),
    ("spherical", "coarse"): FullLoadRecipe(
        "spherical_muscles.toml", guard_damping=True, muscle_stall_rtol=1e-3,
        inversion_guard=0.5,
        record="ran to the end in one of two whole runs on 2 ranks (38 min); the other "
               "failed its final contact phase after 68 min, 0.02 mm from the ball, the "
               "little finger's torque steps failing through their cuts (round-off changes "
               "the path from run to run; forty-second and forty-third sessions); with "
               "tendon_split = 'holzbaur2005' (workflows/spherical_muscles_holzbaur.toml, the "
               "little finger's torques ~27 % lower) both of two whole runs did, in 18-19 "
               "min"),
}

#: (grasp, mesh level) -> the largest workflow muscle_force_scale at which the muscle-driven
#: mode has run to the end there with the shipped recipe's keys where the full load has not
#: (docs/grasp.md, thirty-ninth session)
LIGHT_MUSCLE_RUNS_DONE = {("precision", "coarse"): 0.1, ("spherical", "coarse"): 0.1}

#: what the other (grasp, level) pairs, or those pairs without their recipe's keys, showed
_MUSCLES_SEEN = {
    ("cylindrical", "reduced"): "failed the first quarter of the load after ~40 min on 2 ranks "
                                "without solver.guard_damping (skin cells under the pads trade "
                                "volume), and its final contact phase with "
                                "solver.muscle_stall_rtol = 1e-4",
    ("spherical", "coarse"): "balanced the full load but failed its final contact phase with "
                             "solver.inversion_guard = 0.1 (fat cells between bone and ball "
                             "collapse) and with 0.5 and solver.muscle_stall_rtol = 3e-4 (the "
                             "little finger's torque steps stall at contact kinks); at "
                             "muscle_force_scale = 0.25 that phase cycled without converging "
                             "(with a grasp friction of 1.2 it ran to the end)",
    ("precision", "coarse"): "reached 38-53 % of the load (the index pad slides at the "
                             "friction limit, mu 0.74, and its PIP torque does not balance; at "
                             "muscle_force_scale = 0.25, 77 %; with a grasp friction of 1.2 "
                             "that load ran to the end)",
}

#: (grasp, mesh level) -> the workflow with which the muscle-driven mode has run to the end
#: with the object free to translate (solver.free_object; docs/grasp.md, thirty-fourth session)
FREE_OBJECT_DONE = {("cylindrical", "coarse"): "cylindrical_muscles_free.toml"}

#: what the other (grasp, level) pairs showed with the object free
_FREE_OBJECT_SEEN = {
    ("precision", "coarse"): "failed at muscle_force_scale = 0.1 at every load from 1/4 down "
                             "to 1/64 of it: with the ball on the three digits alone the torque "
                             "Newton asked for steps of 100-250 deg (cut to the trust radius) "
                             "and its residual stalled at 0.13-0.71 (third and forty-sixth "
                             "sessions)",
    ("spherical", "coarse"): "failed with tendon_split = 'holzbaur2005' (the ball recipe that "
                             "ran to the end two of two times held) at every load from 1/4 "
                             "down to 1/64 of it in 33 min: the ball moved at the trust radius "
                             "(0.52 mm) in 32 of 53 torque steps, at times into the ring and "
                             "middle fingers (9-19 N on each at 1/8 and 1/32 of the load); the "
                             "quarter's FE solves failed through four cuts (cells under the "
                             "distal skin at J 0.08-0.1), the smaller loads' torque residual "
                             "stalled at 0.78-1.07 (forty-sixth session)",
}

_GIVES_UP = "a run that gives up writes the last balanced load's results, marked partial"


def muscles_mode_caveat(mode: str, grasp: str, level: str,
                        solver: SolverSpec | None = None, force_scale: float = 1.0) -> str:
    """What the muscle-driven mode has shown for this grasp, mesh level, (if given) solver
    keys and muscle force scale, when that is less than a finished run ("" otherwise, and in
    the angles mode): said before the run, so nobody waits 40 minutes for a failure that is
    already known (docs/grasp.md)."""
    if mode != "muscles":
        return ""
    if solver is not None and solver.free_object and (grasp, level) not in FREE_OBJECT_DONE:
        seen = _FREE_OBJECT_SEEN.get((grasp, level), "has not been run")
        done = "; ".join(f"{g} at '{lv}' (workflows/{w})"
                         for (g, lv), w in FREE_OBJECT_DONE.items())
        return (f"with the object free (solver.free_object = true) the muscle-driven mode has "
                f"run to the end only as: {done}; {grasp} at '{level}' {seen} "
                f"(docs/grasp.md); {_GIVES_UP}")
    recipe = FULL_LOAD_RECIPES.get((grasp, level))
    if recipe is not None and recipe.met_by(solver):
        return (f"with the keys of workflows/{recipe.workflow} the muscle-driven {grasp} grasp "
                f"at '{level}' {recipe.record}; see docs/grasp.md; {_GIVES_UP}"
                ) if recipe.record else ""
    light = LIGHT_MUSCLE_RUNS_DONE.get((grasp, level))
    if light is not None and force_scale <= light:
        return ""
    seen = _MUSCLES_SEEN.get((grasp, level), "has not been run")
    if light is not None:
        seen += f" (at muscle_force_scale <= {light:g} it ran to the end)"
    done = "; ".join(f"{g} at '{lv}'" + (f" with {r.keys()}" if r.keys() else "")
                     + f" (workflows/{r.workflow})"
                     for (g, lv), r in FULL_LOAD_RECIPES.items())
    return (f"at the full EMG load the muscle-driven mode has run to the end ('done') only "
            f"as: {done}; {grasp} at '{level}' {seen} (docs/grasp.md); {_GIVES_UP}")


def _peak_rss_GB() -> float:
    """This process's peak resident memory so far (GB, 1e9 bytes; Linux reports KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def run_workflow(workflow: Workflow | str | Path, *, mesh: str | None = None,
                 out_dir: Path | str | None = None, comm: MPI.Comm = MPI.COMM_WORLD,
                 materials: Mapping[str, Ogden] | None = None,
                 muscle_scale: Mapping[str, float] | None = None,
                 loading: str | None = None, progress: bool | Callable[[str], None] = True
                 ) -> GraspResult:
    """Run a grasp workflow; returns per-region metrics and the summary. Writes outputs to
    ``out_dir`` (rank 0) if given. ``materials`` overrides the skin / subcutaneous Ogden sets;
    ``muscle_scale`` multiplies muscle forces (e.g. {"FDS": 1.1}), on top of the workflow's
    ``muscle_force_scale``."""
    from handfe.anatomy import build_hand, load_subject
    from handfe.anatomy.meshing import failure_cause
    from handfe.emg import muscle_forces
    from handfe.io import write_json
    from handfe.parallel import rprint

    t_start = time.perf_counter()
    stages: dict[str, float] = {}
    wf = workflow if isinstance(workflow, Workflow) else load_workflow(workflow)
    level = mesh or wf.mesh
    mode = loading or wf.loading
    # the workflow as run: everything downstream (the FE scene too) reads this one
    wf = replace(wf, mesh=level, loading=mode)
    # settings of the other mode, which this one would drop without a word
    other = "angles" if mode == "muscles" else "muscles"
    dropped = angles_only_settings(wf) if other == "angles" else muscles_only_settings(wf)
    if dropped:
        raise ConfigError(f"{wf.source or '<workflow>'}: loading = {mode!r} does not use "
                          f"{', '.join(dropped)} (the {other} mode's); drop them or run the "
                          f"{other} mode")
    if callable(progress):
        say = progress
    elif progress:
        def say(msg: str) -> None:
            rprint(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", comm=comm)
    else:
        def say(msg: str) -> None:
            return None
    out = Path(out_dir) if out_dir is not None else None
    if out is not None and comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    grasp = wf.grasp_spec()
    subject_dir = wf.subject_dir()
    materials = dict(materials or {})
    bad = set(materials) - {"skin", "subcutaneous"}
    if bad:
        raise InputError(f"materials: unknown tissue(s) {sorted(bad)} (skin, subcutaneous)")
    skin = materials.get("skin") or Ogden.skin(nu=wf.solver.nu)
    subcut = materials.get("subcutaneous") or Ogden.subcutaneous(nu=wf.solver.nu)
    summary: dict[str, Any] = {"workflow": wf.source, "grasp": grasp.name, "subject": str(
        subject_dir), "loading": mode, "mesh": level, "element": wf.element,
        "stages_s": stages, "status": "running",
        # every key the run used (the workflow's over its base's and the defaults), so a run
        # folder says how to redo it
        "settings": asdict(wf)}

    def checkpoint(status: str) -> None:
        summary["status"] = status
        summary["wall_s"] = time.perf_counter() - t_start
        if out is not None and comm.rank == 0:
            write_json(out / "summary.json", summary)

    stage = "setup"
    scene = None
    try:
        # -- posture and muscle forces
        t0 = time.perf_counter()
        from handfe.grasp.mechanics import opened_pose

        measured, pose_src = measured_pose(wf, grasp, subject_dir)
        pose = opened_pose(measured, grasp.digits, grasp.opening_deg)
        subject = load_subject(subject_dir)
        forces = {m: f for m, (f, _sd) in muscle_forces(
            subject_dir, grasp.name, trial=wf.trial or None).items()}
        scale = dict(muscle_scale or {})
        unknown = set(scale) - set(forces)
        if unknown:
            raise InputError(f"muscle_scale: unknown muscle(s) {sorted(unknown)} "
                             f"(known: {', '.join(forces)})")
        forces = {m: f * wf.muscle_force_scale * scale.get(m, 1.0) for m, f in forces.items()}
        summary.update(pose_source=pose_src, opening_deg=grasp.opening_deg,
                       muscle_forces_N=forces, muscle_force_scale=wf.muscle_force_scale,
                       muscle_scale=scale,
                       tendon_split=wf.tendon_split if mode == "muscles" else None)
        stages["posture_emg"] = time.perf_counter() - t0
        of = f" ({wf.muscle_force_scale:g} x EMG)" if wf.muscle_force_scale != 1.0 else ""
        say(f"{grasp.name}: posture from {pose_src}; muscle forces{of} "
            + ", ".join(f"{m} {f:.0f} N" for m, f in forces.items()))
        if mode == "muscles" and wf.tendon_split != "equal":
            from handfe.anatomy.geometry import FINGERS
            from handfe.anatomy.tables import tendon_shares

            shares = tendon_shares(wf.tendon_split)
            say(f"tendon split {wf.tendon_split} ({' / '.join(FINGERS)}): " + "; ".join(
                f"{m} " + " / ".join(f"{shares[m, d]:.3f}" for d in FINGERS)
                for m in ("FDS", "FDP")))
        # a per-muscle factor above 1 (sensitivity) takes that muscle past the scale run
        caveat = muscles_mode_caveat(mode, grasp.name, level, wf.solver,
                                     wf.muscle_force_scale * max([1.0, *scale.values()]))
        if caveat:
            summary["caveat"] = caveat
            say(f"note: {caveat}")
        # -- object placement and rigid pre-closing on the skin surface of the opened posture
        stage = "placement"
        t0 = time.perf_counter()
        from handfe.anatomy.meshing import skin_surface
        from handfe.anatomy.skeleton import build_skeleton
        from handfe.grasp.mechanics import DigitArc, closed_pose, pre_close
        from handfe.grasp.outputs import region_of

        surf0 = skin_surface(subject, pose, digits=grasp.digits, level="coarse", comm=comm)
        H = build_skeleton(subject, pose).hand_frame
        obstacle = make_obstacle(grasp.object, H)
        regions = grasp.object.placement_regions or tuple(grasp.digits) + ("palm",)
        s = wf.solver
        vreg: list[tuple[str, str] | None] = [None] * len(surf0.points)
        for tri, code in zip(surf0.triangles, surf0.codes, strict=True):
            for v in tri:
                if vreg[v] is None:
                    vreg[v] = region_of(code)
        arc = DigitArc(subject, pose, grasp.digits, surf0.points,
                       [r or ("palm", "") for r in vreg])
        res = None
        err = None
        if comm.rank == 0:
            try:
                reach = {d: arc.swept(d, s.preclose_max_deg) for d in grasp.digits} \
                    if s.pre_close else None
                res = place_object(obstacle, grasp.object, H, surf0, regions, grasp.source,
                                   reach=reach)
            except ConfigError as exc:
                err = str(exc)
            except Exception as exc:  # rank 0 only: report, never hang rank 1
                err = f"object placement failed on rank 0: {type(exc).__name__}: {exc}"
        err = comm.bcast(err, root=0)
        if err:
            raise ConfigError(err)
        shift, clearance, region_gaps = comm.bcast(res, root=0)
        summary["object"] = {"shape": grasp.object.shape, "shift_mm": shift.tolist(),
                             "clearance_opened_mm": clearance,
                             "gap_per_region_opened_mm": region_gaps,
                             "centre_world_mm": (np.asarray(getattr(obstacle, "centre", (
                                 np.nan,) * 3)) + shift).tolist()}
        say(f"object {grasp.object.shape} placed {np.linalg.norm(shift):.1f} mm from its start, "
            f"clearance {clearance:.2f} mm (opened posture)")
        if s.pre_close:
            closing = pre_close(arc, lambda x: obstacle.gap_normal(x, shift)[0],
                                s.preclose_clearance_mm, max_deg=s.preclose_max_deg)
            pose_opened = pose
            pose = closed_pose(pose, closing)
            summary["pre_closing"] = {d: {"closing_deg": c.closing_deg,
                                          "gap_before_mm": c.gap_before_mm,
                                          "gap_after_rigid_estimate_mm": c.gap_after_mm,
                                          "reaches_object": c.reaches}
                                      for d, c in closing.items()}
            say("rigid pre-closing to " + f"{s.preclose_clearance_mm:g} mm: " + ", ".join(
                f"{d} +{c.closing_deg:.1f} deg" + ("" if c.reaches else " (misses the object)")
                for d, c in closing.items()))
            missing = [d for d, c in closing.items() if not c.reaches]
            if missing:
                raise ConfigError(
                    f"{grasp.source}: digit(s) {missing} cannot reach the object by flexion "
                    f"within {s.preclose_max_deg:g} deg: move the object (centre_mm, search_mm) "
                    "or drop the digit from 'digits'")
        stages["placement"] = time.perf_counter() - t0
        # -- mesh
        stage = "mesh"
        t0 = time.perf_counter()
        # an OCC/HXT failure at the pre-closed posture (two skin surfaces that nearly touch make
        # the surface mesh self-intersect) is retried at nearby postures: 0.3 deg less closing,
        # then 3/4, 1/2 and none of the pre-closing; the FE closing covers the difference
        tries = [(1.0, 0.0), (1.0, 0.3), (0.75, 0.0), (0.5, 0.0), (0.0, 0.0)] \
            if s.pre_close else [(1.0, 0.0)]
        failures = []
        for k, (factor, minus) in enumerate(tries):
            if k:
                pose = closed_pose(pose_opened, {d: replace(c, closing_deg=max(
                    0.0, factor * c.closing_deg - minus)) for d, c in closing.items()})
                say(f"meshing failed ({failure_cause(failures[-1])}); retrying with "
                    f"{factor:g} x the pre-closing - {minus:g} deg")
            try:
                model = build_hand(subject, pose, digits=grasp.digits, level=level, comm=comm)
                break
            except InputError as exc:
                failures.append(str(exc))
                if k == len(tries) - 1 or "meshing failed" not in str(exc):
                    raise
        if failures:  # the angles in "pre_closing" were scaled by factor, minus minus_deg
            summary["meshing_failures"] = failures
            summary["pre_closing_used"] = {"factor": factor, "minus_deg": minus}
        stages["mesh"] = time.perf_counter() - t0
        n_cells = model.mesh.topology.index_map(3).size_global
        skipped = [d for d in ("thumb", "index", "middle", "ring", "little")
                   if d not in grasp.digits]
        summary["mesh_cells"] = n_cells
        summary["mesh_from_cache"] = bool(model.quality.get("from_cache", False))
        from_mesh = model.quality.get("skipped")
        summary["skipped"] = {"digits": skipped, **(from_mesh if isinstance(from_mesh, dict)
                                                    else {})}
        say(f"mesh ({level}, digits {', '.join(grasp.digits)}): {n_cells} tets in "
            f"{stages['mesh']:.1f} s" + (f"; skipped {', '.join(skipped)}" if skipped else ""))
        H = model.skeleton.hand_frame
        gaps_start: dict[str, float] | str | None = None
        if comm.rank == 0:
            try:
                gaps_start = start_gaps(obstacle, shift, model.surface)
            except Exception as exc:  # rank 0 only: report, never hang rank 1
                gaps_start = f"starting gaps failed on rank 0: {type(exc).__name__}: {exc}"
        gaps_start = comm.bcast(gaps_start, root=0)
        if isinstance(gaps_start, str):
            raise InputError(gaps_start)
        summary["object"]["gap_per_region_start_mm"] = gaps_start
        worst = min(gaps_start, key=gaps_start.get)
        say("starting gaps on the mesh: " + ", ".join(f"{r} {g:.2f}" for r, g in
                                                      gaps_start.items()) + " mm")
        if gaps_start[worst] < 0.0:
            raise ConfigError(
                f"{grasp.source}: the object intersects the meshed skin of the {worst} by "
                f"{-gaps_start[worst]:.2f} mm in the starting posture: raise "
                "solver.preclose_clearance_mm or opening_deg, or move the object")
        # -- FE problem
        stage = "fe-setup"
        t0 = time.perf_counter()
        scene = GraspFE(model, grasp, wf, skin, subcut, obstacle, shift, pose, subject, forces,
                        say, measured)
        if s.palm_force_N > 0.0 and mode == "angles":
            res = None
            if comm.rank == 0:
                try:
                    res = palm_direction(obstacle, shift, model.surface, grasp.digits)
                except Exception as exc:  # rank 0 only: report, never hang rank 1
                    res = f"the palm's direction failed on rank 0: {type(exc).__name__}: {exc}"
            res = comm.bcast(res, root=0)
            if isinstance(res, str):
                raise InputError(res)
            scene.palm_direction, scene.palm_gap_mm, scene.digit_push_per_N = res
        stages["fe_setup"] = time.perf_counter() - t0
        summary["dofs"] = scene.problem.num_dofs()
        say(f"FE problem: {summary['dofs']} dofs ({wf.element}), {len(scene.joints)} released "
            f"joints, {len(scene.lig.rows)} ligament springs")
        checkpoint("running")
        # -- loading
        stage = f"loading ({mode})"
        t0 = time.perf_counter()
        summary["torque_balance"] = TORQUE_BALANCE[mode]
        if mode == "muscles":
            scene.solve_muscles()
        else:
            scene.solve_angles()
        stages["solve"] = time.perf_counter() - t0
        # -- outputs
        stage = "outputs"
        t0 = time.perf_counter()
        regs, tips = _write_outputs(scene, summary, out, wf, grasp, mode, H, comm)
        stages["outputs"] = time.perf_counter() - t0
        summary["peak_memory_GB_per_rank"] = comm.allreduce(_peak_rss_GB(), op=MPI.MAX)
        problems = balance_problems(summary, mode, wf.solver.torque_rtol)
        if problems:
            # never a silently wrong table: the outputs are written, the status says so
            summary["balance_problems"] = problems
            checkpoint("unbalanced")
            say(f"WARNING: the final state is not in equilibrium ({'; '.join(problems)}): "
                "the written results are not a converged solution")
            return GraspResult(regs, summary, out, tips)
        checkpoint("done")
        free = summary.get("object_motion", {}).get("free", False)
        say(f"done in {summary['wall_s']:.1f} s: grip force {summary['grip_force_N']:.1f} N, "
            f"max penetration {summary['max_penetration_mm']:.4f} mm; " + (
                f"net force on the free object {summary['net_object_force_N']:.2g} N" if free
                else f"the object's support takes {summary['net_object_force_N']:.1f} N (the "
                "object is held in space)"))
        if summary["max_penetration_mm"] > wf.solver.penetration_tol_mm:
            say(f"WARNING: the contact ends {summary['max_penetration_mm']:.3g} mm deep, above "
                f"its {wf.solver.penetration_tol_mm:g} mm target: contact areas and pressures "
                "are those of the penalty, not of hard contact")
        return GraspResult(regs, summary, out, tips)
    except (SolverError, InputError, ConfigError) as exc:
        summary["failed_stage"] = stage
        summary["error"] = str(exc)
        # (only the muscles mode sets muscle_load; a failure in a later stage is not partial)
        part = getattr(scene, "muscle_load", 0.0) if stage.startswith("loading") else 0.0
        if isinstance(exc, SolverError) and part > 0.0:
            # the muscles mode restores the last balanced muscle load before it gives up: its
            # results are real equilibria (at part of the EMG torques), so they are written,
            # marked partial (collective: every rank raised the same error)
            summary["partial"] = {"muscle_load": part, "note": (
                f"outputs of the last balanced load: applied torque = holding + {part:.3g} x "
                "(muscle - holding), reported as muscle_Nmm; intermediate loads are balanced "
                "to 10 x torque_rtol (max_relative_torque_residual), before the final Uzawa "
                "phase (max_penetration_mm; with muscle_uzawa, each load ends with the "
                "pads within step_penetration_mm)")}
            say(f"writing the partial results at muscle load {part:.3g}")
            try:
                _write_outputs(scene, summary, out, wf, grasp, mode, H, comm)
            except Exception as exc2:  # keep the original error; say why there is no partial
                summary["partial"]["error"] = f"{type(exc2).__name__}: {exc2}"
        checkpoint("failed")
        if isinstance(exc, SolverError):
            raise SolverError(f"grasp {grasp.name}, stage {stage}: {exc}",
                              load_step=exc.load_step, load_factor=exc.load_factor,
                              residual=exc.residual) from None
        raise


# what the per-joint torque residuals of summary.json mean in each loading mode
TORQUE_BALANCE = {
    "muscles": "solved: at each released joint the muscle (EMG), ligament and tissue/contact "
               "torques balance (joints.*.residual_Nmm, relative_residual)",
    "angles": "not imposed: the joint angles are prescribed; joints.*.residual_Nmm is the "
              "muscle torque (EMG) minus what the ligaments and the tissue/contact reactions "
              "take at that posture, i.e. how far the measured forces are from balancing it",
}


def _write_outputs(scene: GraspFE, summary: dict[str, Any], out: Path | None, wf: Workflow,
                   grasp, mode: str, H, comm: MPI.Comm) -> tuple[dict, dict]:
    """Metrics of the current state into ``summary``; regions.csv, fingertips.csv,
    pressure.png and the fields into ``out`` (rank 0 writes; collective)."""
    from handfe.anatomy.meshing import REGIONS
    from handfe.grasp.outputs import METRICS
    from handfe.io import write_csv

    regs, fd = scene.metrics()
    summary.update(scene.report())
    total_f = np.sum([regs[r]["force_vector_N"] for r in REGIONS], axis=0)
    # net force on the object (|sum|: what the held object's support takes; 0 only if the
    # digits' forces balance each other, 5-21 N at 5 N per digit, docs/grasp.md) and the grip
    # force = sum of the regions' contact force magnitudes
    summary["net_object_force_N"] = float(np.linalg.norm(total_f))
    summary["grip_force_N"] = float(sum(regs[r]["normal_force_N"] for r in REGIONS))
    summary["contact_force_vector_N"] = total_f.tolist()
    tips = {d: {"mean_pressure_kPa": regs[f"{d}_distal"]["mean_pressure_kPa"],
                "peak_pressure_kPa": regs[f"{d}_distal"]["peak_pressure_kPa"],
                "contact_area_mm2": regs[f"{d}_distal"]["contact_area_mm2"],
                "loaded_area_mm2": regs[f"{d}_distal"]["loaded_area_mm2"]}
            for d in REGIONS if d != "palm"}
    if out is not None:
        rows = [{"region": k, **{m: v[m] for m in METRICS}} for k, v in regs.items()]
        if comm.rank == 0:
            write_csv(out / "regions.csv", rows)
            write_csv(out / "fingertips.csv", [{"digit": d, **v} for d, v in tips.items()])
        if wf.outputs.png:
            from handfe.grasp.outputs import pressure_map_png
            pressure_map_png(fd, H.R, out / "pressure.png", comm,
                             title=f"{grasp.name} grasp ({mode}), contact pressure",
                             facets_npz=out / "pressure_facets.npz")
        if wf.outputs.fields:
            scene.write_fields(out / "fields.xdmf")
    return regs, tips


class DigitStepLimiter:
    """Trust radius (rad) per digit for the torque Newton on the joint angles.

    No joint moves more than its digit's radius per iteration: a joint with little to push
    against has a tiny tangent and would otherwise take a huge step. Each digit's part of the
    step is scaled as a whole (clipping joint by joint turns the coupled Newton direction
    within a chain), digits separately: they meet only through the palm's tissue, and one
    digit's soft direction must not shrink another digit's step to nothing. A digit whose
    new step points back against its last one (it overshot: along a soft direction, e.g. a
    finger reconfiguring about its stuck pad, or against a pad that stiffens faster than the
    tangent says) gets half its last step as radius (bisection-like), down to
    ``min_fraction`` x ``max_rad``; one that was capped and keeps going the same way gets its
    radius doubled, up to ``max_rad``. The radius starts at ``start_fraction`` x ``max_rad``: a
    pad pressed into the object stiffens faster than the tangent predicts, and a first full
    step there failed the FE solve through four cuts (~4 min on the coarse pinch)."""

    def __init__(self, digits: list[str], max_rad: float, min_fraction: float = 1e-4,
                 start_fraction: float = 1.0):
        self.names = np.array(digits)
        self.max_rad = max_rad
        self.min_rad = max_rad * min_fraction
        self.radius = {g: max_rad * start_fraction for g in dict.fromkeys(digits)}
        self.prev: dict[str, tuple[np.ndarray, bool]] = {}

    def update(self, d_new: np.ndarray) -> dict[str, float]:
        """Adapt the radii to the direction of the new step (rad, per joint); returns them."""
        for g, r in self.radius.items():
            if g in self.prev:
                p, capped = self.prev[g]
                dot = float(d_new[self.names == g] @ p)
                p_max = float(np.abs(p).max(initial=0.0))
                # a reversal after a step far inside the radius is not an overshoot to bisect:
                # the group was nearly balanced and another group's step (the object's, the
                # other digits') moved its residual; halving that tiny step froze the object
                # of a stand-in pinch at 1e-3 mm steps while its force was 12 % off
                if dot < 0.0 and p_max >= 0.1 * r:
                    r = max(0.5 * min(r, p_max), self.min_rad)
                elif capped and dot > 0.0:
                    r = min(2.0 * r, self.max_rad)
                self.radius[g] = r
        return dict(self.radius)

    def accept(self, d: np.ndarray, d_newton: np.ndarray) -> np.ndarray:
        """Scale each digit's part of ``d`` into its radius and remember it."""
        d = np.array(d, dtype=float)
        for g, r in self.radius.items():
            m = self.names == g
            big = float(np.abs(d[m]).max(initial=0.0))
            if big > r:
                d[m] *= r / big
            self.prev[g] = (d[m].copy(), float(np.abs(d_newton[m]).max(initial=0.0)) > r)
        return d


def response_ratios(predicted: np.ndarray, actual: np.ndarray, groups: list[str],
                    previous: dict[str, float], lo: float = 0.05) -> dict[str, float]:
    """Per group: the part of the predicted residual change (tangent x step) that the model
    delivered, <actual, predicted> / |predicted|^2, clipped to [``lo``, 1] and to at least half
    the ``previous`` ratio (one odd step - a pad that slipped once - must not make the next
    step 20x Newton's: on the pinch that overshot and failed the FE solve); a group whose
    predicted change is negligible (< 1e-9 of the largest) keeps its previous ratio."""
    names = np.array(groups)
    scale = float(np.abs(predicted).max(initial=0.0))
    out = {}
    for g in dict.fromkeys(groups):
        m = names == g
        pp = float(predicted[m] @ predicted[m])
        if pp <= (1e-9 * scale) ** 2:
            out[g] = previous.get(g, 1.0)
            continue
        floor = max(lo, 0.5 * previous.get(g, 1.0))
        out[g] = float(np.clip(float(actual[m] @ predicted[m]) / pp, floor, 1.0))
    return out


STALL_WINDOW = 8  # torque Newton iterations without a 10 % drop of the residual = a stall
# mm: length that turns the object's translation into an angle-like unknown of the torque
# Newton (t / L) and its force into a torque-like residual (F x L); the trust radius of the
# object is then max_step_deg (rad) x L (3 deg: 0.52 mm)
OBJECT_LENGTH_MM = 10.0


def damped_newton_step(K: np.ndarray, g: np.ndarray, groups: list[str],
                       radius: dict[str, float]) -> np.ndarray:
    """Solve (K + Lambda) d = g with Lambda = diag(lambda per group) >= 0, the smallest damping
    for which each group's own block gives max|d| <= its radius (a Levenberg-Marquardt /
    trust-region step; K = stiffness = -d(residual)/d(angle), N mm/rad).

    Along a soft direction (a stiffness much below lambda) the step shrinks to ~g/lambda, while
    along the stiff ones (pressing the pad into the object) it stays Newton's: scaling the
    plain Newton step instead, the soft direction's huge component would leave the stiff
    directions no progress at all."""
    names = np.array(groups)
    lam = np.zeros(len(g))
    for grp in dict.fromkeys(groups):
        m = names == grp
        Kg, gg, r = K[np.ix_(m, m)], g[m], radius[grp]
        n = int(m.sum())

        def size(x: float, Kg=Kg, gg=gg, n=n) -> float:
            try:
                return float(np.abs(np.linalg.solve(Kg + x * np.eye(n), gg)).max(initial=0.0))
            except np.linalg.LinAlgError:
                return float("inf")

        if size(0.0) <= r:
            continue
        lo, hi = 0.0, float(np.linalg.norm(Kg, 2) + np.sqrt(n) * np.abs(gg).max() / r)
        while size(hi) > r:
            hi *= 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if size(mid) <= r else (mid, hi)
        lam[m] = hi
    try:
        return np.linalg.solve(K + np.diag(lam), g)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(K + np.diag(lam), g, rcond=None)[0]


def closing_aim_N(target_N: float, rtol: float) -> float:
    """The force (N) a closing step aims a digit at: the middle of the lower half of the band
    [(1 - rtol), (1 + rtol)] x ``target_N``, so that a step that falls a little short stops the
    digit and one that goes a little over is not redone."""
    return (1.0 - 0.5 * rtol) * target_N


# a closing step aims at most this x the digit's current force (the pinch's index went from
# 0.68 N to 7.7 N in one step aimed at 4.9 N; docs/grasp.md, thirty-first session)
CLOSING_FORCE_RATIO = 3.0


def secant_closing_increment(last: tuple[float, float] | None, closed_deg: float,
                             force_N: float, target_N: float, rtol: float,
                             max_step_deg: float,
                             max_ratio: float = CLOSING_FORCE_RATIO) -> float:
    """Next closing angle of a digit (deg): the log-force secant through its last two
    (closed angle, force) pairs ``last`` and (``closed_deg``, ``force_N``), aimed at
    (1 - rtol / 2) x ``target_N`` or ``max_ratio`` x ``force_N``, whichever is smaller,
    within [0.02, 1] x ``max_step_deg``; ``max_step_deg`` without a usable secant (first
    step, no force yet, force not rising). A pad's force can grow faster than exponentially
    with the angle once it presses (0.5 deg took the pinch's middle finger from 3 to 40 N),
    so a long extrapolation overshoots and the step is redone; ``max_ratio`` keeps it short."""
    if last is None:
        return max_step_deg
    c0, f0 = last
    if not (f0 > 1e-3 * target_N and force_N > 1.01 * f0 and closed_deg > c0):
        return max_step_deg
    g = math.log(force_N / f0) / (closed_deg - c0)
    aim = min(closing_aim_N(target_N, rtol), max_ratio * force_N)
    return float(np.clip(math.log(aim / force_N) / g, 0.02 * max_step_deg, max_step_deg))


# a closing step whose Uzawa updates take a digit past this x digit_force_N is redone at once;
# a smaller overshoot is measured after the updates (a regula falsi on a mid-phase force,
# which is a lower bound, lands high)
OVERSHOOT_ABANDON = 1.5


def redo_closing_fraction(start_N: float, over_N: float, target_N: float, rtol: float,
                          repeat: int = 0) -> float:
    """Fraction of an overshooting closing increment to redo it with: the log-force regula
    falsi between the step's start (fraction 0, ``start_N``) and the overshoot (fraction 1,
    ``over_N``), aimed at (1 - rtol / 2) x ``target_N``, within [0.05, 0.95]. ``repeat``
    overshoots of the same step before this one halve the start's log-distance to the aim
    each (Illinois), so a concave log-force curve does not keep the retries landing high.

    In the logs of 11 redone steps (coarse and default pinch, reduced sphere; docs/grasp.md)
    the plain log regula falsi fraction (0.75-0.95) was within 0.03 of the one that lands on
    the aim in 9, judged by interpolating between the tries; the former cap of 0.7 made all
    11 land 0.1-2.5 N short of it."""
    aim = closing_aim_N(target_N, rtol)
    g0 = math.log(max(start_N, 1e-3 * target_N) / aim) * 0.5 ** repeat
    g1 = math.log(over_N / aim)
    if not (g0 < 0.0 < g1):
        return 0.05
    return float(np.clip(-g0 / (g1 - g0), 0.05, 0.95))


class GraspFE:
    """The FE model of one grasp and its two loading paths."""

    def __init__(self, model, grasp, wf: Workflow, skin, subcut, obstacle, shift, pose,
                 subject, forces, say, measured=None):
        from dolfinx import mesh as dmesh

        from handfe.contact_problem import RigidContact
        from handfe.grasp.fe import BoneBC, GraspProblem, TwoFormNewton
        from handfe.grasp.mechanics import Kinematics, Ligaments, muscle_torques, released_joints
        from handfe.grasp.outputs import describe_cell

        self.model, self.grasp, self.wf, self.say = model, grasp, wf, say
        self.obstacle = obstacle
        self.problem = GraspProblem(model, skin, subcut, element=wf.element)
        bones = list(model.bones) or [k[5:] for k in model.tags if k.startswith("bone_")]
        self.bc = BoneBC(self.problem, model, bones)
        ft = model.facet_tags
        sel = np.isin(ft.values, model.groups["skin_outer"])
        skin_tags = dmesh.meshtags(model.mesh, 2, ft.indices[sel],
                                   np.ones(int(sel.sum()), dtype=np.int32))
        self.skin_tags = skin_tags
        E_eff = 3.0 * min(skin.shear_modulus_MPa, subcut.shear_modulus_MPa)
        s = wf.solver
        self.contact = RigidContact(self.problem, obstacle, skin_tags, 1, mu=grasp.friction,
                                    penalty_factor=s.penalty_factor,
                                    penetration_tol_mm=s.penetration_tol_mm,
                                    gap_tol_mm=s.gap_tol_mm, E_eff_MPa=E_eff,
                                    adaptive_penalty=s.adaptive_penalty or None,
                                    augmented_friction=s.augmented_friction,
                                    stick_ratio=s.stick_ratio, stick_tol_mm=s.stick_tol_mm,
                                    quadrature=s.contact_quadrature,
                                    friction_smoothing=s.friction_smoothing)
        self.contact.translation.value = np.asarray(shift, dtype=float)
        self.contact.max_penalty_growth = 4.0  # stronger growth ruins Newton on the hand
        # contact Newton often converges linearly for a while (active set settling): 40
        # iterations before a cut wastes less than restarting a halved step
        self.solver = TwoFormNewton(self.problem, max_it=40,
                                    guard_keep=s.inversion_guard)
        # a failed solve's note says where its smallest cell was ("2.7 mm under the
        # thumb/proximal skin"), not only its J
        self.solver.locate = lambda centre: describe_cell(model, centre)
        self.solver.damping = s.guard_damping
        # Newton on the contact kinks can cycle between two active sets at a residual of
        # 1e-5 N (whole-hand cylinder, 1 Dec 2026): below 1e-4 N (out of balance force, N;
        # 2e-5 of a 5 N digit force) that state is accepted, counted in the summary
        self.solver.stall_atol = 1e-4
        self.solver.line_search = s.newton_linesearch
        self._fallback_ls = "basic" if s.newton_linesearch == "bt" else "bt"
        self.joints = released_joints(grasp.digits)
        self.kin = Kinematics(subject, pose, self.joints)
        m = measured or pose
        self.theta_measured = np.array([m[j.dof] for j in self.joints])
        self.lig = Ligaments(self.kin.skel0, set(bones))
        self.forces = forces
        self.tau_muscle = muscle_torques(forces, self.joints, wf.tendon_split)
        self.theta = self.kin.theta0.copy()
        self.motions = self.kin.motions(self.kin.skel0)
        self.steps: list[dict] = []
        self.outer_iterations = 0
        self.augmentations = 0
        self.cuts = 0
        self.torque: dict[str, np.ndarray] = {}
        self.at_limit = np.zeros(len(self.joints), dtype=bool)
        # (PIP index, DIP index, ratio) pairs of the muscles mode's DIP-PIP coupling
        self.coupled: list[tuple[int, int, float]] = []
        self._substep = 1.0  # fraction of a load step tried first (adapted in _go_to)
        # while true, accepted FE solves do not mark the friction return mapping due (the
        # torque Newton with solver.muscle_friction_history = "load")
        self._hold_history = False
        self.stalled: dict[str, str] = {}  # angles mode: digits whose closing step failed
        self._dw: np.ndarray | None = None  # last accepted state increment (secant predictor)
        self._dbc = 0.0  # norm of the bone displacement increment of that step
        # muscles mode: the object's translation is an unknown (solver.free_object)
        self.object_free = wf.loading == "muscles" and s.free_object
        self.translation0 = np.asarray(shift, dtype=float).copy()
        self.force_target = np.zeros(3)  # N: net contact force the object must carry
        self._t_response: list[np.ndarray] = []  # du/dt_c (tangent predictor of a translation)
        # dw/dtheta_i per rad (solver.tangent_predictor) at the start of a torque step, or None
        self._theta_response: list[np.ndarray] | None = None
        # which predictor started each FE solve of a bone step (the smallest residual wins)
        self.predictor_wins = {"extension": 0, "secant": 0, "tangent": 0}
        # friction return mappings dropped because the solve that applied them failed
        self.dropped_mappings = 0

    # -- one boundary-condition step with cutting
    def _go_to(self, theta: np.ndarray, *, label: str, max_cuts: int = 6,
               translation: np.ndarray | None = None) -> None:
        """Move the bones to the joint angles ``theta`` (deg) and the object to ``translation``
        (mm; default: where it is), in sub-steps cut on failure (each with the same fraction of
        both); SolverError after ``max_cuts`` cuts, with everything back at the step's start
        (converged sub-steps are not kept: the joint angles stay those of the state)."""
        start = self._snapshot()
        theta = self.kin.clamp(theta)
        dtheta = np.radians(theta - self.theta)  # the whole step, rad
        skel = self.kin.skeleton(theta)
        target = self.kin.motions(skel)
        prev = self.motions
        t_prev = np.array(self.contact.translation.value, dtype=float)
        t_target = t_prev if translation is None else np.asarray(translation, dtype=float)
        t_conv = t_prev.copy()
        w0 = self.problem.w.x.array.copy()  # last converged state (with ghosts)
        # start from the sub-step size that worked last time (no 25 wasted iterations on a
        # full step that failed just before); it grows again after easy solves
        blend, done_frac = min(1.0, self._substep), 0.0
        cuts = 0
        bc_conv = self.bc.ubc.x.array.copy()  # bone displacement of the last converged state
        while done_frac < 1.0 - 1e-12:
            # the friction return mapping due from the last accepted state changes the stick
            # anchors and tangential multipliers (a full tangential Uzawa update): kept here,
            # so that a solve that fails with it can drop it
            pre_map = self._contact_data() if self.contact.history_due else None
            self.contact.apply_history()
            self._lag_stabilisation()  # from the last converged state, before the predictor
            frac = min(1.0, done_frac + blend)
            self.bc.set(target, frac, prev)
            t_new = t_prev + frac * (t_target - t_prev)
            self.contact.translation.value = t_new
            dbc = self._norm(self.bc.ubc.x.array - bc_conv)
            w = self.problem.w
            self.bc.predict(bc_conv)
            t_add = 0.0
            if self._t_response and np.any(t_new != t_conv):
                # the object's move: the linear response of the last tangent (the elastic
                # extension of a uniform shift of every Dirichlet node is that shift: the pads
                # would not follow the object at all); zero on the Dirichlet dofs
                dt = t_new - t_conv
                n = len(self._t_response[0])
                t_add = sum(dt[c] * self._t_response[c] for c in range(3))
                w.x.array[:n] += t_add
                w.x.scatter_forward()
            # predictors, the one with the smallest residual wins: the elastic extension of
            # the bone motion (robust far from contact, but it pushes loaded pads into the
            # object); the secant one, the last accepted increment scaled by the bone motion
            # (it carries the contact response; overshoots when the pads stiffen); with
            # solver.tangent_predictor in a torque step, the linear response of the last
            # condensed tangent to the joint angles' change (exact to first order)
            cand = {"extension": w.x.array.copy()}
            if self._dw is not None and cuts == 0 and self._dbc > 0.0:
                cand["secant"] = w0 + (dbc / self._dbc) * self._dw
            if self._theta_response is not None:
                cand["tangent"] = self._tangent_prediction(
                    w0, cand["extension"], (frac - done_frac) * dtheta, t_add)
            if len(cand) > 1:
                r = {}
                for name, arr in cand.items():
                    self._set_state(arr)
                    r[name] = self._residual_norm()
                # NaN (inverted cells) never wins; the extension is always finite or nothing is
                best = min(r, key=lambda k: r[k] if np.isfinite(r[k]) else np.inf)
                self._set_state(cand[best])
                self.predictor_wins[best] += 1
            else:
                self.predictor_wins["extension"] += 1
            ok, its, reason = self.solver.solve()
            if not ok and (self._fallback_ls == "bt" or np.isfinite(
                    self.solver.history[-1] if self.solver.history else 0.0)):
                # the first line search failed: backtracking stalls at a kink of the contact
                # law (a small residual that no longer falls), full steps from the step's start
                # may invert cells (NaN). Full steps go on from where backtracking stopped
                # (close to the solution, they jump the kink); else the other line search from
                # the step's start, before cutting the step
                # ... and what kept the steps short, if it was the inversion guard
                hist = " ".join(f"{r:.1e}" for r in self.solver.history[-3:]) \
                    + self.solver.guard_note
                its0 = its
                where = "from there"
                res = self.solver.continue_after_stall()
                if res is None:
                    self._set_state(w0)
                    self.bc.predict(bc_conv)
                    where = "from the step's start"
                    res = self.solver.solve(self._fallback_ls)
                ok, its, reason = res
                self.say(f"    {label}: {self.solver.line_search} line search failed ({hist}); "
                         f"{self._fallback_ls} {where} {'converged' if ok else 'failed too'} "
                         f"({its} iterations)")
                its += its0
            if ok:
                self._dw = self.problem.w.x.array - w0
                self._dbc = dbc
                # the friction return mapping waits for the next solve: applied now, it
                # changes the stick multipliers and a run ending on a failed re-solve would
                # report a state out of balance with them (the reduced spherical grasp
                # ended with an equilibrium error of 0.18 that way)
                if not self._hold_history:
                    self.contact.on_step(frac, None, defer=True)
                self.steps.append({"step": label, "fraction": frac, "newton": its,
                                   "residual": self.solver.history[-1] if self.solver.history
                                   else 0.0})
                done_frac = frac
                if its <= 8:
                    blend = min(1.0, 2.0 * blend)
                self._substep = blend
                bc_conv = self.bc.ubc.x.array.copy()
                t_conv = t_new.copy()
                w0 = self.problem.w.x.array.copy()
                continue
            self._set_state(w0)
            self.contact.translation.value = t_conv
            cuts += 1
            self.cuts += 1
            # half of what was tried: after a sub-step that doubled the size, the remainder
            # (clamped to the step's end) may be less than the size
            blend = 0.5 * (frac - done_frac)
            self._substep = blend
            hist = " ".join(f"{r:.1e}" for r in self.solver.history[-6:])
            self.say(f"    {label}: Newton failed ({reason}; last residuals {hist}); cutting the "
                     f"step to {blend:.3g}")
            if pre_map is not None:
                # with the return mapping in it, a failed solve fails again at any cut (runs K
                # and SQ: the first torque step after a failed round of the final phase, cut
                # to 1/4096 and 1/32): the anchors and multipliers the converged state was
                # solved with are kept, and the next accepted solve marks a new mapping due
                self._set_contact_data(pre_map)
                self.contact.history_due = False
                self.dropped_mappings += 1
                self.say(f"    {label}: the friction return mapping due from the last accepted "
                         "state is dropped")
            if cuts > max_cuts:
                last = self.solver.history[-1] if self.solver.history else float("nan")
                # back to the step's start: a converged sub-step left the bones part of the way
                # with the joint angles (and so the next step's blend) still at the start, and
                # the next step then began by jumping the bones back (SQr1: the first torque
                # step of the final phase's second round failed at 1/16 and 1/32)
                self._restore(start)
                self.bc.set(prev, 1.0, prev)
                raise SolverError(f"load step '{label}' did not converge after {cuts} cuts "
                                  f"(reached {done_frac:.3g} of the step, back to its start): "
                                  f"{reason}",
                                  load_step=len(self.steps) + 1, load_factor=done_frac,
                                  residual=last)
        self.theta = theta
        self.motions = target
        self.skel = skel

    def _lag_stabilisation(self) -> None:
        """``solver.stabilisation_modulus = "tangent"`` (default): the p1-p1s stabilisation
        takes each tissue cell's incremental shear modulus at the current (converged) state
        for the next solve (:meth:`GraspProblem.update_stabilisation`); ``"pressure"``: at
        least ``stabilisation_pressure_factor`` x the cell's |p|; ``"initial"``: mu0, never
        updated. It enters the pressure equation only, so torques and contact forces of a
        state do not depend on it directly. Other elements have no such term."""
        s = self.wf.solver
        if self.wf.element != "p1-p1s":
            return
        if s.stabilisation_modulus == "tangent":
            self.problem.update_stabilisation()
        elif s.stabilisation_modulus == "pressure":
            self.problem.update_stabilisation(s.stabilisation_pressure_factor)

    def _contact_data(self) -> dict[str, Any]:
        """The contact data a solve balances (multipliers, stick anchors, penalty) and whether
        the last step's return mapping is still due."""
        c = self.contact
        data: dict[str, Any] = {"k": float(c.k_n.value), "due": c.history_due}
        for name in ("lambda_n", "lambda_t", "u_ref"):
            f = getattr(c, name)
            data[name] = None if f is None else f.x.array.copy()
        return data

    def _set_contact_data(self, data: dict[str, Any]) -> None:
        c = self.contact
        c.set_penalty(data["k"])
        c.history_due = data["due"]
        for name in ("lambda_n", "lambda_t", "u_ref"):
            if data[name] is not None:
                getattr(c, name).x.array[:] = data[name]

    def _residual_norm(self) -> float:
        """Norm of the Newton residual (Dirichlet rows included) at the current state, N."""
        x = self.problem.w.vector.copy()
        b = x.duplicate()
        self.solver._residual(None, x, b)
        n = b.norm()
        x.destroy()
        b.destroy()
        return float(n)

    def _norm(self, a: np.ndarray) -> float:
        """Global 2-norm of a nodal array (ghosts counted on both ranks: fine for ratios)."""
        return float(np.sqrt(self.problem.comm.allreduce(float(a @ a), op=MPI.SUM)))

    def _stiffen(self) -> None:
        """Penalty continuation after an accepted step: while the penetration exceeds 1.5 x
        ``solver.step_penetration_mm``, raise k_n (by twice the ratio to it, at most x4 per
        re-solve and ``solver.max_penalty_growth`` x its start value) and re-solve from the
        converged state. A soft penalty at first touch (a few contact points on very soft
        tissue) keeps Newton robust; the stiffer one later keeps the penetration - and the
        Uzawa phase - small once the pads have stiffened."""
        c, s = self.contact, self.wf.solver
        if c.uzawa is None:
            return
        k_max = s.max_penalty_growth * c.k_n_value
        for _ in range(4):
            pen = c.uzawa.penetration()
            k = float(c.k_n.value)
            if pen <= 1.5 * s.step_penetration_mm or k >= k_max:
                return
            k_new = min(k * min(4.0, 2.0 * pen / s.step_penetration_mm), k_max)
            balanced = self._contact_data()
            self.contact.apply_history()
            c.set_penalty(k_new)

            def undo(balanced: dict[str, Any] = balanced) -> None:
                self._set_contact_data(balanced)

            if not self._resolve(f"penalty x{k_new / c.k_n_value:.3g} (penetration was "
                                 f"{pen:.3f} mm)", undo):
                return

    def _set_state(self, arr: np.ndarray) -> None:
        """Set the state (u, p) from a local array with ghosts."""
        self.problem.w.x.array[:] = arr
        self.problem.w.x.scatter_forward()

    def _tangent_prediction(self, w0: np.ndarray, ext: np.ndarray, dtheta: np.ndarray,
                            t_add: np.ndarray | float = 0.0) -> np.ndarray:
        """The state ``w0`` (last converged, with ghosts) moved by the linear response to the
        joint-angle change ``dtheta`` (rad) of the last condensed tangent (plus ``t_add``, the
        owned entries of a free object's move), with the bone nodes where the exact rigid
        motion puts them (``ext``, the extension predictor, has them); ghosts from their
        owners (:meth:`_set_state` scatters)."""
        z = self._theta_response
        n = len(z[0])
        arr = w0.copy()
        arr[:n] += sum(dt * zi for dt, zi in zip(dtheta, z, strict=True)) + t_add
        bcd = self.bc.bc_dofs_W
        arr[bcd] = ext[bcd]
        return arr

    def _resolve(self, what: str, undo: Callable[[], None]) -> bool:
        """Re-solve after a change of the contact data; on failure restore the last converged
        state and call ``undo`` (which restores the data). Says how it went."""
        w0 = self.problem.w.x.array.copy()
        ls = self.wf.solver.resolve_linesearch
        self._lag_stabilisation()
        ok, its, reason = self.solver.solve(ls)
        if not ok:
            its0 = its
            # full steps only after backtracking stopped short of its budget: in the run logs
            # of sessions 29-32 no re-solve's continuation converged (15 of 15 failed, 10 of
            # them 41-80 iterations in all, after a crawl at lambda ~0.1 with NaN full steps);
            # the state and data are restored after a failure either way (docs/grasp.md)
            res = self.solver.continue_after_stall() if its0 < self.solver.max_it else None
            if res is not None:
                what += " (bt stalled, full steps from there)"
            elif ls == "basic":
                self._set_state(w0)
                res = self.solver.solve("bt")
                what += " (full steps failed, bt)"
            if res is not None:
                ok, its, reason = res
                its += its0
        self.say(f"    {what}: Newton {'converged' if ok else 'failed: ' + reason} "
                 f"({its} iterations)")
        if not ok:
            self._set_state(w0)
            undo()
        return ok

    def augment(self, tol_mm: float | None = None, *, creep: bool = True,
                stop: Callable[[], bool] | None = None, max_updates: int | None = None,
                max_depth_mm: float = 0.0) -> None:
        """Uzawa updates until the penetration (and, if ``creep``, the stick creep) is <= the
        tolerance (``tol_mm``, default the contact's), or ``stop()`` is true after a re-solve,
        at most ``max_updates`` (default ``solver.max_augment``). With ``max_depth_mm`` > 0 an
        update at a penetration deeper than that is under-relaxed to ``max_depth_mm`` /
        penetration of its multiplier change.
        A re-solve that fails restores the last converged state and multipliers and stops (the
        penetration reached is reported, never hidden)."""
        c = self.contact
        if tol_mm is not None or not creep:
            tols = c.penetration_tol_mm, c.stick_tol_mm
            if tol_mm is not None:
                c.penetration_tol_mm = c.stick_tol_mm = tol_mm
            if not creep:
                c.stick_tol_mm = math.inf
            try:
                self.augment(stop=stop, max_updates=max_updates, max_depth_mm=max_depth_mm)
            finally:
                c.penetration_tol_mm, c.stick_tol_mm = tols
            return
        prev = last_rate = float("nan")
        doubled = False  # the last update doubled the penalty (the "< 2x fall" rule below)
        grow = True  # that rule; off for the rest of the phase once a doubling did not help
        # under-relaxation of the multiplier change that the last re-solve needed: later updates
        # of this phase start from it (a full update that Newton could not follow once tends to
        # fail again, each failure costing ~40 iterations; 0.25 x then converges in a few)
        relax0 = 1.0
        for _ in range(self.wf.solver.max_augment if max_updates is None else max_updates):
            if stop is not None and stop():
                return
            balanced = self._contact_data()  # what the state balances: restored on failure
            mapped = c.history_due
            self.contact.apply_history()
            # an under-relaxed update starts from the stick data before the due return mapping
            # (itself a full tangential update): relaxing the Uzawa change alone left the
            # mapping at full strength in every halved re-solve
            start = (c.lambda_n.x.array.copy(), balanced["lambda_t"], balanced["u_ref"])
            k = float(c.k_n.value)
            # changes the multipliers (and k_n), not the state; with uzawa_tangential_relax < 1
            # a mapping just made is the update's tangential step
            t_relax = self.wf.solver.uzawa_tangential_relax
            done, pen = c.augment(True, tangential=not (mapped and t_relax < 1.0))
            if done:
                self._set_contact_data(balanced)
                return
            self.augmentations += 1
            if c.adaptive_penalty is not None and math.isfinite(prev):
                rate = pen / prev
                if doubled and not rate < last_rate:
                    # the doubling did not speed up the fall: the deepest node is likely pushed
                    # only through Gauss points off the object (a vertex at a patch's rim),
                    # whose pressure lambda - k g a larger k lowers; doubling on kept
                    # lambda / k bounded and stalled the matched-force cylinder at 0.023 mm
                    # for 12 updates (docs/grasp.md, thirty-fifth session)
                    grow = False
                doubled = grow and rate > 0.5
                if doubled:
                    # the pressure-following penalty is too soft for a stiffened pad (the
                    # penetration falls by < 2x per update): at least double it
                    c.set_penalty(max(float(c.k_n.value), 2.0 * k))
                last_rate = rate
            prev = pen

            def undo(start: tuple = start, k: float = k) -> None:
                self._relax_multipliers(0.0, start, start)
                c.set_penalty(k)

            creep = f", stick creep {c.last_creep_mm:.4f} mm" if c.lambda_t is not None else ""
            what = (f"Uzawa update {self.augmentations} (penetration was "
                    f"{c.last_penetration_mm:.4f} mm{creep})")
            new = tuple(None if f is None else f.x.array.copy()
                        for f in (c.lambda_n, c.lambda_t, c.u_ref))
            cap = 1.0  # max_depth_mm's share of this update; the halving floor scales with it
            if max_depth_mm > 0.0 and c.last_penetration_mm > max_depth_mm:
                cap = max_depth_mm / c.last_penetration_mm
            relax = first = min(relax0, cap)
            if relax < 1.0:
                self._relax_multipliers(relax, start, new)
                c.set_penalty(k)
            elif t_relax < 1.0 and c.lambda_t is not None:
                # the stick data's change crawled at full strength (docs/grasp.md, thirty-third
                # session); the normal update and the penalty stay full
                self._relax_multipliers(t_relax, start, new, normal=False)
                what += f", tangential x{t_relax:.3g}"
            ok = self._resolve(what if relax == 1.0 else f"{what} x{relax:.3g}", undo)
            while not ok and relax > 0.3 * cap:
                # under-relaxed update from the restored state: half the multiplier change,
                # the old penalty (a full update that Newton cannot follow ended the phase)
                relax /= 2.0
                self._relax_multipliers(relax, start, new)
                ok = self._resolve(f"{what} x{relax:.3g}", undo)
            if not ok:
                self._set_contact_data(balanced)
                return
            doubled = doubled and float(c.k_n.value) > k  # an under-relaxed update kept k
            relax0 *= relax / first  # what the failures needed; the depth cap is per update

    def _relax_multipliers(self, relax: float, start: tuple, new: tuple, *,
                           normal: bool = True) -> None:
        """(lambda_n, lambda_t, u_ref) = start + ``relax`` x (new - start); None entries (no
        friction, no augmented friction) are left alone, and lambda_n if not ``normal``.
        Between the anchors and multipliers before and after a return mapping, a slipping
        node's traction stays on the cone."""
        c = self.contact
        for name, a, b in zip(("lambda_n", "lambda_t", "u_ref"), start, new, strict=True):
            if name == "lambda_n" and not normal:
                continue
            f = getattr(c, name)
            if f is not None and a is not None and b is not None:
                f.x.array[:] = a + relax * (b - a)

    def _joint_geometry(self, skel):
        from handfe.grasp.mechanics import joint_axis_centre
        return [joint_axis_centre(skel, j) for j in self.joints], \
            [j.distal_bones for j in self.joints]

    def max_torque_residual(self, tq: dict[str, np.ndarray] | None = None) -> float:
        """Largest relative torque residual over the released joints not held at a limit
        (of :meth:`torques`, or of ``tq`` when given)."""
        tq = self.torques() if tq is None else tq
        return float(np.where(self.at_limit, 0.0, tq["relative"]).max(initial=0.0))

    def torques(self) -> dict[str, np.ndarray]:
        from handfe.grasp.fe import torques_from

        skel = self.kin.skeleton(self.theta)
        ac, ds = self._joint_geometry(skel)
        R = self.solver.full_residual()
        t_tis = torques_from(R.getArray(), self.bc, ac, ds, self.problem.comm)
        R.destroy()
        t_lig = self.lig.torques(self.kin.motions(skel), skel, self.joints)
        g = self.tau_muscle + t_lig + t_tis
        # DIP-PIP coupling (muscles mode): the coupling carries what the DIP does not balance
        # (-g at the DIP) and passes c x that to the PIP (no work along the coupled motion)
        t_cpl = np.zeros(len(g))
        for ip, idp, c in self.coupled:
            t_cpl[idp] = -g[idp]
            t_cpl[ip] = c * g[idp]
        g = g + t_cpl
        scale = np.maximum.reduce([np.abs(self.tau_muscle), np.abs(t_lig), np.abs(t_tis),
                                   np.abs(t_cpl), np.full(len(g), 1e-9)])
        return {"muscle": self.tau_muscle, "ligament": t_lig, "tissue": t_tis,
                "coupling": t_cpl, "residual": g, "relative": np.abs(g) / scale}

    def _coupling_matrix(self) -> np.ndarray:
        """B (joints x coordinates) with d(theta) = B d(q): a coupled DIP follows c x its PIP."""
        cols = [i for i in range(len(self.joints)) if i not in {d for _, d, _ in self.coupled}]
        B = np.zeros((len(self.joints), len(cols)))
        for k, i in enumerate(cols):
            B[i, k] = 1.0
        for ip, idp, c in self.coupled:
            B[idp, cols.index(ip)] = c
        return B

    def _region_dofs(self, region: str) -> list[np.ndarray]:
        """Owned displacement dofs (per component) of one region's outer skin (a digit or
        the palm)."""
        from dolfinx import fem

        from handfe.grasp.outputs import region_of

        cache = self.__dict__.setdefault("_rdofs", {})
        if region not in cache:
            W = self.problem.W
            ft = self.model.facet_tags
            fdim = self.model.mesh.topology.dim - 1
            n_owned = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
            codes = np.array(self.model.groups["skin_outer"])
            region_of_code = np.array([region_of(c)[0] for c in codes])
            f = ft.indices[np.isin(ft.values, codes[region_of_code == region])]
            dd = []
            for i in range(3):
                x = fem.locate_dofs_topological(W.sub(0).sub(i), fdim, f)
                dd.append(x[x < n_owned])
            cache[region] = dd
        return cache[region]

    def _digit_dofs(self) -> dict[str, list[np.ndarray]]:
        """Owned displacement dofs (per component) of each participating digit's outer skin."""
        return {d: self._region_dofs(d) for d in self.grasp.digits}

    def _contact_sums(self, groups: list[list[np.ndarray]]) -> np.ndarray:
        """Contact residual summed per component over each group of owned dofs (one (x, y, z)
        row per group, N), over ranks: one assembly for all groups."""
        from dolfinx.fem import petsc as fem_petsc
        from petsc4py import PETSc

        Rc = fem_petsc.assemble_vector(self.solver.L[1])
        Rc.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        r = Rc.getArray()
        local = np.array([[r[x].sum() for x in g] for g in groups])
        Rc.destroy()
        return np.array(self.problem.comm.allreduce(local, op=MPI.SUM))

    def _contact_force_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """Contact force (N) the skin exerts on the object: (net vector, one vector per
        participating digit), summed over ranks."""
        dd = self._digit_dofs()
        tot = self._contact_sums([dd[d] for d in self.grasp.digits] + [self.bc.all_comp_dofs])
        return tot[-1], tot[:-1]

    def palm_force(self) -> np.ndarray:
        """Contact force (N, vector) the palm's skin exerts on the object, summed over ranks."""
        return self._contact_sums([self._region_dofs("palm")])[0]

    def digit_forces(self) -> dict[str, float]:
        """Magnitude of the contact force (N) each participating digit exerts on the object."""
        _, per = self._contact_force_sums()
        return {d: float(np.linalg.norm(v)) for d, v in zip(self.grasp.digits, per, strict=True)}

    def object_residual(self) -> tuple[np.ndarray, float]:
        """Net contact force on the object minus the force it must carry (N), and the grip
        (sum of the digits' force magnitudes, N) that scales it."""
        net, per = self._contact_force_sums()
        return net - self.force_target, float(np.linalg.norm(per, axis=1).sum())

    def _snapshot(self) -> dict[str, Any]:
        """Everything a closing step changes (state, bone data, contact multipliers, penalty,
        stick anchors, predictor), for :meth:`_restore`."""
        c = self.contact
        snap = {"theta": self.theta.copy(), "motions": self.motions,
                "skel": getattr(self, "skel", None), "w": self.problem.w.x.array.copy(),
                "ubc": self.bc.ubc.x.array.copy(),
                "dw": self._dw, "dbc": self._dbc,
                "translation": np.array(c.translation.value, dtype=float),
                "contact": self._contact_data(),
                # the lagged stabilisation modulus the state was solved with ("tangent")
                "mu0": self.problem.mu0.x.array.copy()}
        return snap

    def _restore(self, snap: dict[str, Any]) -> None:
        c = self.contact
        self.theta, self.motions, self.skel = snap["theta"].copy(), snap["motions"], snap["skel"]
        self._set_state(snap["w"])
        self.bc.ubc.x.array[:] = snap["ubc"]
        c.translation.value = snap["translation"]
        self._dw, self._dbc = snap["dw"], snap["dbc"]
        self._set_contact_data(snap["contact"])
        self.problem.mu0.x.array[:] = snap["mu0"]

    def _closing_increment(self, last: tuple[float, float] | None, closed: float,
                           force: float) -> float:
        s = self.wf.solver
        if not s.closing_secant:
            return s.closing_step_deg
        return secant_closing_increment(last, closed, force, s.digit_force_N,
                                        s.digit_force_rtol, s.closing_step_deg)

    def _overshoots(self, active: list[str], before: dict[str, float],
                    limit_N: float | None = None) -> tuple[list[str], dict[str, float]]:
        """Digits of ``active`` that were below ``digit_force_N`` (forces ``before``) and are
        now past ``limit_N`` (default (1 + rtol) x digit_force_N); and the digit forces now."""
        s = self.wf.solver
        if limit_N is None:
            limit_N = (1.0 + s.digit_force_rtol) * s.digit_force_N
        now = self.digit_forces()
        return [d for d in active if now[d] > limit_N and before[d] < s.digit_force_N], now

    def solve_angles(self) -> None:
        """Kinematic closing (:meth:`_close_digits`), then the Uzawa phase removes the remaining
        penetration; the closing with ``solver.closing_atol_N``, then tight solves."""
        with self._loose():
            if self.wf.solver.palm_force_N > 0.0:
                self._press_palm()
            self._close_digits()
        self._tighten()
        self._final_phase()
        self.digit_force_N = self.digit_forces()
        self.torque = self.torques()

    def _final_phase(self) -> None:
        """Uzawa updates to the penetration target with tight re-solves (a failed one restores
        a tight state and its data: loose updates then one tight solve had ended the reduced
        spherical grasp unbalanced when that solve failed, docs/grasp.md). If the phase ends
        above the target (a failed re-solve, or max_augment), it goes on with loose updates and
        one tight solve; that result is kept only if the tight solve converges and the
        penetration fell, otherwise the tight state and its contact data come back."""
        self.augment()
        c = self.contact
        if c.uzawa is None or self.wf.solver.closing_atol_N <= self.solver.atol:
            return
        tol, pen = c.penetration_tol_mm, c.uzawa.penetration()
        if pen <= tol:
            return
        w0, data0 = self.problem.w.x.array.copy(), self._contact_data()
        self.say(f"  final phase stopped at {pen:.4f} mm (target {tol:g} mm): loose updates "
                 "from there, then one tight solve")
        with self._loose():
            self._scale_loose(self.digit_forces())
            # to the penetration target only: the stick creep that kept the tight phase going
            # is not what this continuation is for (reduced cylinder: it stayed at 0.02 mm
            # over the loose updates, ~100 s each, after the penetration was at 0.004 mm)
            self.augment(creep=False)
        ok = self._tighten()
        pen1 = c.uzawa.penetration()
        if ok and pen1 < pen:
            self.say(f"  kept: penetration {pen1:.4f} mm")
            return
        self._set_state(w0)
        self._set_contact_data(data0)
        self.steps.append({"step": "restored tight state", "fraction": 1.0, "newton": 0,
                           "residual": self._residual_norm(), "converged": True})
        why = f"penetration {pen1:.4f} mm" if ok else "the tight solve failed"
        self.say(f"  not kept ({why}): back to the tight state at {pen:.4f} mm")

    @contextlib.contextmanager
    def _loose(self):
        """Newton solves inside stop at ``solver.closing_atol_N`` (intermediate states: a
        closing step only has to tell the digit forces to a few per cent)."""
        a = self.wf.solver.closing_atol_N
        tight, stall = self.solver.atol, self.solver.stall_atol
        self._tight_tol = (tight, stall)
        if a > tight:
            self.solver.set_atol(a)
            self.solver.stall_atol = max(stall, a)
        try:
            yield
        finally:
            self._tight_tol = None
            self.solver.set_atol(tight)
            self.solver.stall_atol = stall

    def _scale_loose(self, forces: Mapping[str, float]) -> None:
        """Inside :meth:`_loose`: the tolerance follows the load, 2e-3 x the sum of the digit
        forces (N), between the tight tolerance and ``solver.closing_atol_N`` (at first touch
        the digits carry 0.01-0.1 N: a fixed 1e-2 N would hide their forces)."""
        tt = getattr(self, "_tight_tol", None)
        cap = self.wf.solver.closing_atol_N
        if tt is None or cap <= tt[0]:
            return
        a = float(np.clip(2e-3 * sum(forces.values()), tt[0], cap))
        self.solver.set_atol(a)
        self.solver.stall_atol = max(tt[1], a)

    def _tighten(self, *, stalled: bool = False) -> bool:
        """After loose solves: Newton to the tight tolerance with the contact data the state
        was solved with (a pending friction return mapping stays pending), so the reported
        state balances them. On failure the loose state is kept and ``final_residual_N`` in the
        summary says how far from balance it is. True if it converged.

        ``stalled`` (the muscles mode's final state): whenever the residual is above the
        tight stall tolerance (the torque Newton accepts FE stalls up to
        ``muscle_stall_rtol`` x the grip: coarse cylinder, 8.4e-3 N at 134 N, which left the
        object's equilibrium error at 6.3e-5), not only after loose closing solves."""
        if not stalled and self.wf.solver.closing_atol_N <= self.solver.atol:
            return True
        w0 = self.problem.w.x.array.copy()
        if not stalled:
            # not for the final state: a new stabilisation modulus is new data (the coarse
            # cylinder's final state went from ~1e-2 to 0.41 N, and the solve from there failed)
            self._lag_stabilisation()
        r0 = self._residual_norm()
        if stalled and r0 <= self.solver.stall_atol:
            return True
        ok, its, reason = self.solver.solve()
        if not ok:
            its0 = its
            res = self.solver.continue_after_stall()
            if res is not None:
                ok, its, reason = res
                its += its0
        if not ok:
            self._set_state(w0)
        self.steps.append({"step": "tight solve", "fraction": 1.0, "newton": its,
                           "residual": self._residual_norm(), "converged": bool(ok)})
        self.say(f"  tight solve from {r0:.1e} N: " + (
            f"converged ({its} iterations)" if ok else
            f"failed ({reason}, {its} iterations): the state keeps its {r0:.1e} N residual"))
        return bool(ok)

    def _press_palm(self) -> None:
        """Angles mode, before the digits close: the object moves along ``palm_direction``
        (the digits' push, towards the palm) until the palm carries ``solver.palm_force_N``
        within the digits' band ``digit_force_rtol``. The first move takes it past the palm's
        starting gap by half a step; then log-force secant steps of at most ``palm_step_mm``
        (a step past the band redone smaller), with the digits' Uzawa updates after each, at
        most ``palm_travel_mm`` in all. A step that fails through its cuts ends the press there
        (``palm_press.stalled`` in the summary); the digits then close against the object
        where it is."""
        s = self.wf.solver
        d = np.asarray(self.palm_direction, dtype=float)
        t0 = np.array(self.contact.translation.value, dtype=float)
        target, rtol = s.palm_force_N, s.digit_force_rtol
        f_stop, f_over = (1.0 - rtol) * target, (1.0 + rtol) * target
        far = max(OVERSHOOT_ABANDON, 1.0 + rtol) * target
        travel, k = 0.0, 0
        last: tuple[float, float] | None = None
        f = float(np.linalg.norm(self.palm_force()))
        # what the digits would push with at digit_force_N each along their start normals
        push_N = s.digit_force_N * float(getattr(self, "digit_push_per_N", float("nan")))
        self.palm_press: dict[str, Any] = {"target_N": target, "direction": d.tolist(),
                                           "start_gap_mm": float(self.palm_gap_mm),
                                           "digits_push_estimate_N": push_N}
        self.say(f"palm: the object moves along the digits' push (start gap to the palm "
                 f"{self.palm_gap_mm:.2f} mm) until the palm carries {target:g} N (the digits "
                 f"at {s.digit_force_N:g} N each would push with ~{push_N:.1f} N). "
                 "Experimental: on the coarse cylinder three of the five digits then stayed "
                 "short of their force (docs/grasp.md, forty-seventh session)")
        while f < f_stop and travel < s.palm_travel_mm - 1e-9:
            k += 1
            self._scale_loose({"palm": f})
            if last is None and f <= 1e-3 * target:
                inc = max(self.palm_gap_mm, 0.0) + 0.5 * s.palm_step_mm
            else:
                inc = secant_closing_increment(last, travel, f, target, rtol, s.palm_step_mm)
            inc = min(inc, s.palm_travel_mm - travel)
            snap = self._snapshot()
            f_new = f
            for retry in range(4):
                try:
                    self._go_to(self.theta, label=f"palm {k}",
                                translation=t0 + (travel + inc) * d)
                except SolverError as exc:
                    self._restore(snap)
                    self.palm_press["stalled"] = str(exc)
                    self.say(f"    the palm's press stops here: {exc}")
                    inc = 0.0
                    break
                if s.step_uzawa:
                    self.augment(s.step_penetration_mm, creep=False, stop=lambda: bool(
                        np.linalg.norm(self.palm_force()) > far))
                else:
                    self._stiffen()
                f_new = float(np.linalg.norm(self.palm_force()))
                if f_new <= f_over or retry == 3:
                    break
                self.say(f"    palm {f_new:.2f} N overshoots {target:g} N: step redone smaller")
                self._restore(snap)
                inc *= redo_closing_fraction(f, f_new, target, rtol, retry)
            if inc == 0.0:
                break
            last, travel, f = (travel, f), travel + inc, f_new
            if self.steps:
                self.steps[-1]["palm_force_N"] = f
            self.say(f"  palm step {k}: object {travel:.2f} mm in, palm {f:.2f} N")
        self.palm_press.update({"travel_mm": travel, "force_N": f, "steps": k})

    def _close_digits(self) -> None:
        """Each digit whose contact force is below ``digit_force_N`` closes its released joints
        by ``closing_step_deg`` per load step (the others hold), until every digit carries its
        force or has closed by ``closing_deg`` (or sits at its joint limits)."""
        s = self.wf.solver
        theta = self.theta.copy()
        closed = dict.fromkeys(self.grasp.digits, 0.0)
        digit_of = np.array([j.digit for j in self.joints])
        k = 0
        last: dict[str, tuple[float, float]] = {}  # digit -> (closed, force) before its last step
        f_stop = (1.0 - s.digit_force_rtol) * s.digit_force_N
        # past this force a step is redone before its Uzawa updates end (see below)
        far = max(OVERSHOOT_ABANDON, 1.0 + s.digit_force_rtol) * s.digit_force_N
        # digits that close one at a time: a step of several digits that fails is redone digit
        # by digit, so one digit whose step Newton cannot solve does not stop the others
        solo: set[str] = set()
        said = -1
        while True:
            forces = self.digit_forces()
            self._scale_loose(forces)
            active = [d for d in self.grasp.digits if forces[d] < f_stop
                      and closed[d] < s.closing_deg - 1e-9 and d not in self.stalled
                      and np.any(theta[digit_of == d] < self.kin.hi[digit_of == d] - 1e-9)]
            if k and said != k:
                self.say(f"  closing step {k}: digit forces " + ", ".join(
                    f"{d} {f:.2f}" for d, f in forces.items()) + " N")
                said = k
                if self.steps:  # the closing history in summary.json: forces after each step
                    self.steps[-1]["digit_force_N"] = dict(forces)
            if not active:
                break
            if solo & set(active):
                active = [next(d for d in active if d in solo)]
            k += 1
            inc = {}
            for d in active:
                inc[d] = min(self._closing_increment(last.get(d), closed[d], forces[d]),
                             s.closing_deg - closed[d])
                last[d] = (closed[d], forces[d])
            snap = self._snapshot()
            retreat = s.closing_secant
            repeat = dict.fromkeys(active, 0)  # overshoots of this step so far, per digit
            for retry in range(4):
                theta = self.theta.copy()
                for d in active:
                    theta[digit_of == d] += inc[d]
                theta = self.kin.clamp(theta)
                try:
                    self._go_to(theta, label=f"closing {k} ({', '.join(active)})",
                                max_cuts=3 if len(active) > 1 else 6)
                except SolverError as exc:
                    # back to the last converged step; several digits: redo them one at a
                    # time; one digit: it holds where it is and the others go on (the
                    # summary says which digits stalled and why)
                    self._restore(snap)
                    if len(active) > 1:
                        solo.update(active)
                        self.say(f"    {', '.join(active)}: closing one digit at a time")
                    else:
                        self.stalled.update({d: str(exc) for d in active})
                        self.say(f"    {', '.join(active)} stop closing here: {exc}")
                    inc = {}
                    break
                # a digit past its force band (the pad stiffens abruptly once it presses): back
                # to the step's start and a log-force regula falsi for the overshooting digits.
                # The Uzawa updates only add force, but a force measured before they end is a
                # lower bound, and a regula falsi on it lands high (the pinch's index: 6.7 N
                # after the first update, then 5.6 and 5.3 N on the redone steps). So a step
                # is abandoned before its updates end only when a digit is past
                # OVERSHOOT_ABANDON x digit_force_N; a smaller one is measured after them
                over: list[str] = []
                f_new: dict[str, float] = {}
                check = retreat and retry < 3
                for phase in ("solve", "uzawa"):
                    if phase == "uzawa":
                        # penetration only (stick creep is the final Uzawa phase's job)
                        if s.step_uzawa:
                            self.augment(s.step_penetration_mm, creep=False,
                                         stop=(lambda a=active, f=forces: bool(
                                             self._overshoots(a, f, far)[0])) if check else None)
                        else:
                            self._stiffen()
                    if check:
                        over, f_new = self._overshoots(active, forces)
                    if over and (phase == "uzawa" or max(f_new[d] for d in over) > far):
                        break
                if not over:
                    break
                self.say("    " + ", ".join(f"{d} {f_new[d]:.2f} N" for d in over)
                         + f" overshoots {s.digit_force_N:g} N: step redone smaller")
                self._restore(snap)
                for d in over:
                    inc[d] *= redo_closing_fraction(forces[d], f_new[d], s.digit_force_N,
                                                    s.digit_force_rtol, repeat[d])
                    repeat[d] += 1
            for d in inc:
                closed[d] += inc[d]
            theta = self.theta.copy()
        self.closing_deg = closed
        self.digit_force_N = forces

    def solve_muscles(self) -> None:
        """Muscle-driven equilibrium by torque homotopy.

        1. The digits close kinematically until each presses with ``digit_force_N`` (as in the
           angles mode, without its final Uzawa phase): every digit is in contact, so every
           released joint has a tissue stiffness to push against. With
           ``muscle_frictionless_closing`` (default) the closing runs at mu = 0 and the stick
           anchors are then set on the closed state, so the pads start without shear.
        2. At that posture the joints hold the torque ``tau_hold = -(ligament + tissue)``.
           The applied joint torque goes from ``tau_hold`` to the muscle torque in load steps
           (``muscle_steps``; a step whose torque Newton fails is halved); at each step Newton
           on the released joint angles (condensed FE tangent + ligament tangent) balances
           applied + ligament + tissue torque. Starting each step from a balanced state keeps
           it short; starting from the pre-closed posture (no contact, no stiffness) did not
           converge.
        3. Uzawa updates remove the penetration, and the balance is re-established (three
           times at most), so the reported residual is the one with the final multipliers."""
        s = self.wf.solver
        c = self.contact
        frictionless = s.muscle_frictionless_closing and c.u_ref is not None
        if frictionless:
            mu = c.mu
            self.say(f"  closing frictionless (mu {mu:g} from the torque load on)")
            c.set_friction(0.0)
            self.closing_mu = 0.0
        try:
            with self._loose():
                self._close_digits()
            self._tighten()  # the holding torques come from the tissue residual
        finally:
            if frictionless:
                c.set_friction(mu)
        if frictionless:
            # stick anchors on the closed state: zero tangential traction, so the state with
            # friction on is the frictionless one and needs no re-solve
            c.release_stick()
        if s.dip_pip_coupling > 0.0:
            idx = {j.name: i for i, j in enumerate(self.joints)}
            self.coupled = [(idx[f"{j.digit}_pip"], i, s.dip_pip_coupling)
                            for i, j in enumerate(self.joints)
                            if j.name.endswith("_dip") and f"{j.digit}_pip" in idx]
        tau_m = self.tau_muscle.copy()
        tq = self.torques()
        tau_hold = -(tq["ligament"] + tq["tissue"])
        f_hold = np.zeros(3)
        if getattr(self, "object_free", False):
            # the support carries this force on the object in the closed posture; it fades
            # with the muscle load, so at full load the digits alone hold the object
            f_hold, _ = self._contact_force_sums()
            self.say("  object free to translate; force on it in the closed posture "
                     + " ".join(f"{x:+.2f}" for x in f_hold) + " N (fades with the load)")
        self.say("  muscle torques (N mm): " + ", ".join(
            f"{j.name} {m:.0f} (holding {h:.0f})" for j, m, h in
            zip(self.joints, tau_m, tau_hold, strict=True)))
        done, ds = 0.0, 1.0 / s.muscle_steps
        self.muscle_load = 0.0
        # the penalty may double before a load; the retry of a failed load keeps the penalty
        # the last balanced load had (on the coarse cylinder with muscle_uzawa, 2.52 -> 5.03
        # N/mm3 before each retry of loads 0.5, 0.375, 0.3125 left the first torque step's FE
        # solve failing with the step cut to 1/4096: the stiffer penalty, not the load)
        retry = False
        try:
            while done < 1.0 - 1e-12:
                lam = min(1.0, done + ds)
                self.tau_muscle = tau_hold + lam * (tau_m - tau_hold)
                self.force_target = (1.0 - lam) * f_hold
                snap = self._snapshot()
                self.say(f"  muscle load {lam:.3f}")
                if not retry:
                    self._penalty_to_pressure()
                ok, why = self._balance_torques(10.0 * s.torque_rtol if lam < 1.0
                                                else s.torque_rtol, label=f"muscle load {lam:.3g}")
                if ok:
                    done = self.muscle_load = lam
                    retry = False
                    continue
                self._restore(snap)
                retry = True
                ds *= 0.5
                self.cuts += 1
                if ds < 1.0 / (16 * s.muscle_steps):
                    raise SolverError(f"muscle load {lam:.3g} (from {done:.3g}): {why}",
                                      load_step=len(self.steps) + 1, load_factor=done)
                self.say(f"    muscle load {lam:.3g} failed ({why}): step halved")
            self._final_muscle_phase()
        except SolverError:
            if self.muscle_load > 0.0:
                # the state is the last balanced load's (restored): its torques, with the
                # torque applied there, are what a partial report shows
                self.tau_muscle = tau_hold + self.muscle_load * (tau_m - tau_hold)
                self.force_target = (1.0 - self.muscle_load) * f_hold
                self.torque = self.torques()
                # the end stops of that state, not of the failed balance after it (the coarse
                # cylinder's thumb MCP, at its limit, was reported with a residual of 0.31)
                self._set_limits(self.torque["residual"])
                self.digit_force_N = self.digit_forces()
            raise
        finally:
            self.tau_muscle = tau_m
        self.digit_force_N = self.digit_forces()
        self.torque = self.torques()

    def _final_muscle_phase(self) -> None:
        """After the full muscle load balanced: Uzawa updates remove the penetration
        (``solver.muscle_final_uzawa``: at the fixed posture between balances, or one after
        each torque step), the balance is re-established (three rounds at most) and the final
        tight solve follows. Raises :class:`SolverError` (state restored to the last balanced
        one) when the balance fails."""
        s = self.wf.solver
        interleaved = s.muscle_final_uzawa == "interleaved"
        if not interleaved:
            # interleaved: the Uzawa updates after each torque step close the gap with the
            # penalty the full load was balanced with; raising it first (2.23 -> 4.47
            # N/mm3 on the coarse cylinder) failed its fixed-posture re-solve in runs C, D
            # and E alike (55-80 Newton iterations, 65-117 s) and gave the data back
            self._penalty_to_pressure(resolve=True)
        balanced = self._snapshot()  # a failed round reports this, not an unbalanced state
        depth = {"uzawa_depth_mm": s.penetration_tol_mm} if interleaved else {}
        for _ in range(3):
            if not interleaved:
                with self._grip_stall():
                    self._scale_stall_to_grip()
                    self.augment()
            ok, why = self._balance_torques(s.torque_rtol, label="muscle load 1 (Uzawa)",
                                            **depth)
            pen = self.contact.uzawa.penetration() if self.contact.uzawa else 0.0
            if ok:
                balanced = self._snapshot()
            if ok and pen <= s.penetration_tol_mm:
                break
        if not ok:
            self._restore(balanced)
            raise SolverError(f"torque balance at full muscle load: {why}",
                              load_step=len(self.steps) + 1, load_factor=1.0)
        self._tighten(stalled=True)

    def _penalty_to_pressure(self, *, resolve: bool = False) -> None:
        """``solver.muscle_penalty_follows_pressure``: before a muscle load (and the final Uzawa
        phase) raise k_n towards the larger of adaptive_penalty x the pads' peak pressure /
        facet size and peak pressure / step_penetration_mm (the first alone allows 0.4 mm of
        penalty depth on the coarse hand's 4 mm facets), at most ``muscle_penalty_growth`` x
        per call, keeping the tractions of the balanced state (:meth:`RigidContact.stiffen`).
        Without it k_n stays the closing's (~1 N per digit) while the EMG load presses the pads
        20-30x harder, and they sink in by mm: the coarse cylinder reached the full load 2.1 mm
        deep, and each Uzawa round at full load then moved the pads so far that a digit
        lifted off.

        ``resolve`` (the final phase): re-solve with the stiffer penalty at once, giving the
        data back if that fails. Before a muscle load the first torque step's FE solve does
        it, moving the bones too: a re-solve at the fixed posture failed there (coarse
        cylinder, 1.12 -> 2.23 N/mm3 at load 0.625) and kept the penalty from growing."""
        c = self.contact
        if not (self.wf.solver.muscle_penalty_follows_pressure and c.uzawa is not None
                and c.adaptive_penalty is not None):
            return
        k = float(c.k_n.value)
        p = c.uzawa.peak_pressure()
        target = p * max(c.adaptive_penalty / c.h_mm, 1.0 / self.wf.solver.step_penetration_mm)
        # at most muscle_penalty_growth (2) x per load: 7x at once (0.53 -> 3.91 N/mm3 on the
        # coarse cylinder) left the FE Newton of the next torque step failing through every cut
        target = min(target, self.wf.solver.muscle_penalty_growth * k)
        if target > k:
            before = self._contact_data()
            off = c.stiffen(target)
            self.say(f"    penalty {k:.3g} -> {target:.3g} N/mm3 (peak pressure {p:.3g} MPa; "
                     f"nodal forces kept to {off:.1e})")
            if resolve:
                # the nodal forces are kept to ~1e-2 only (a curved object): re-solve, so that
                # a state reported without a further solve balances its contact data (the
                # coarse cylinder's final phase, whose Uzawa updates all failed, ended 2.8 N
                # out of balance: object force vs support reactions 0.22 relative)
                self._resolve("re-solve with the stiffer penalty",
                              lambda: self._set_contact_data(before))

    def _balance_torques(self, rtol: float, *, label: str,
                         uzawa_depth_mm: float | None = None) -> tuple[bool, str]:
        """:meth:`_balance` with the FE stall tolerance scaled to the grip (restored after)
        and, with ``solver.muscle_friction_history = "load"``, the friction history held."""
        with self._grip_stall(), self._friction_history_per_load():
            return self._balance(rtol, label=label, uzawa_depth_mm=uzawa_depth_mm)

    @contextlib.contextmanager
    def _friction_history_per_load(self):
        """``solver.muscle_friction_history = "load"``: inside, accepted FE solves leave the
        stick anchors and tangential multipliers alone, so every torque iteration of a load
        balances the contact data the load started from (a return mapping still due from
        the state before is applied by the first solve); on leaving, the return mapping of
        the state reached is marked due, for the next load or Uzawa phase. With updates
        after every solve the data changed between torque iterations (slipping nodes gave
        less than the tangent promised), and the relative torque residual of the coarse
        cylinder at full EMG load chattered at 3e-3 - 7e-3 with steps of 0.01 deg."""
        if self.wf.solver.muscle_friction_history != "load":
            yield
            return
        self._hold_history = True
        try:
            yield
        finally:
            self._hold_history = False
            if self.contact.u_ref is not None:  # frictionless: no history
                self.contact.on_step(1.0, None, defer=True)

    @contextlib.contextmanager
    def _grip_stall(self):
        """Inside, :meth:`_scale_stall_to_grip` may raise the FE stall tolerance; restored on
        leaving."""
        solver = self.solver
        if solver is None:  # a stand-in without an FE solver
            yield
            return
        base = solver.stall_atol
        self._stall_base = base
        try:
            yield
        finally:
            solver.stall_atol = base

    def _scale_stall_to_grip(self) -> None:
        """FE solves of the torque Newton accept a backtracking stall at <= max(the base
        tolerance, ``solver.muscle_stall_rtol`` x the grip): at 88 N of grip on the coarse
        cylinder the stiffened pads stalled at 4e-3 - 9e-3 N (1e-4 of the grip, ~0.4 N mm of
        torque at a 50 mm lever against a 1e-3 x 200-2000 N mm torque tolerance), and the
        full steps from there inverted cells through every cut."""
        if self.solver is None:
            return
        grip = float(sum(self.digit_forces().values()))
        self.solver.stall_atol = max(self._stall_base, self.wf.solver.muscle_stall_rtol * grip)

    def _set_limits(self, g: np.ndarray) -> None:
        """Joints held at a limit by the torque residual ``g`` (N mm) pushing past it: end
        stops, whose residual the balance does not count."""
        self.at_limit = ((self.theta >= self.kin.hi - 1e-9) & (g > 0)) | (
            (self.theta <= self.kin.lo + 1e-9) & (g < 0))

    def _balance(self, rtol: float, *, label: str,
                 uzawa_depth_mm: float | None = None) -> tuple[bool, str]:
        """Newton on the released joint angles (and, with a free object, its translation)
        until applied (``tau_muscle``) + ligament + tissue torque is <= ``rtol`` (relative) at
        every free joint and the object's net force is within ``rtol`` of the grip of its
        target; a joint pushed past its limit stays there (end stop). With
        ``uzawa_depth_mm`` (or ``solver.muscle_uzawa``: step_penetration_mm) one Uzawa update
        follows every torque step that leaves the pads deeper than that (with
        ``solver.muscle_uzawa_rtol``: once the torques balance to that), and the balance
        ends only once they are not. Returns (converged, why not)."""
        from handfe.grasp import fe

        s = self.wf.solver
        free_obj = getattr(self, "object_free", False)
        # muscle_uzawa: one Uzawa update after every torque step that leaves the pads deeper
        # than step_penetration_mm (a few tenths of a mm at a time, not one jump at the end)
        if uzawa_depth_mm is None and s.muscle_uzawa:
            uzawa_depth_mm = s.step_penetration_mm
        uzawa = uzawa_depth_mm is not None and self.contact.uzawa is not None
        nj = len(self.joints)
        n_t = 3 if free_obj else 0
        # unknowns (theta in rad, t / OBJECT_LENGTH_MM) and residuals (torques in N mm, the
        # object force x OBJECT_LENGTH_MM): work-conjugate pairs, one trust-radius scale
        L = OBJECT_LENGTH_MM
        names = [j.digit for j in self.joints] + ["object"] * n_t
        limit = DigitStepLimiter(names, math.radians(s.max_step_deg), start_fraction=0.25)
        rel = float("inf")
        hist: list[float] = []
        B = self._coupling_matrix()
        E = np.zeros((nj + n_t, B.shape[1] + n_t))  # (theta, s) = E (q, s)
        E[:nj, :B.shape[1]] = B
        E[nj:, B.shape[1]:] = np.eye(n_t)
        qgroups = [self.joints[int(np.flatnonzero(B[:, k])[0])].digit
                   for k in range(B.shape[1])] + ["object"] * n_t
        rho = {g: 1.0 for g in qgroups}
        last = None  # (residual, predicted change of it) of the last step, (theta, s) space
        for it in range(1, s.max_outer + 1):
            self.outer_iterations += 1
            tq = self.torques()
            g = tq["residual"]
            self._set_limits(g)
            free = ~self.at_limit
            relv = np.where(free, tq["relative"], 0.0)
            rel = float(relv.max(initial=0.0))
            k = int(np.argmax(relv))
            msg = (f"    torque Newton {it}: max relative residual {rel:.2e} at "
                   f"{self.joints[k].name} (applied {tq['muscle'][k]:.0f}, ligament "
                   f"{tq['ligament'][k]:.0f}, tissue/contact {tq['tissue'][k]:.0f} N mm)")
            gx = g
            if free_obj:
                f, grip = self.object_residual()
                rel_f = float(np.linalg.norm(f)) / max(grip, 1e-9)
                msg += (f"; object force off by {np.linalg.norm(f):.3f} N "
                        f"({rel_f:.1e} of the grip {grip:.1f} N)")
                gx = np.concatenate([g, L * f])
                rel = max(rel, rel_f)
            self.say(msg)
            self._scale_stall_to_grip()
            deep = uzawa and self.contact.uzawa.penetration() > uzawa_depth_mm
            if rel <= rtol and not deep:
                self.torque = tq
                return True, ""
            if deep and rel <= max(rtol, s.muscle_uzawa_rtol):
                # balanced (to muscle_uzawa_rtol), but the pads are deeper than the depth
                # asked for: one Uzawa update and the balance goes on from there; the update
                # raises the residual, which is no stall of the Newton steps
                self._one_uzawa_update(uzawa_depth_mm)
                last = None
                hist.clear()
                continue
            if last is not None:
                rho.update(response_ratios(E.T @ last[1], E.T @ (gx - last[0]), qgroups, rho))
            hist.append(rel)
            if len(hist) > STALL_WINDOW and min(hist[-STALL_WINDOW:]) > 0.9 * hist[
                    -STALL_WINDOW - 1]:
                return False, (f"torque residual stalled at {rel:.3g} ({self.joints[k].name}) "
                               f"for {STALL_WINDOW} iterations; {self._friction_use()}")
            skel = self.kin.skeleton(self.theta)
            ac, dsets = self._joint_geometry(skel)
            if free_obj or s.tangent_predictor:
                more = {"responses": True} if s.tangent_predictor else {}
                T = fe.condensed_tangent(self.solver, self.bc, ac, dsets, self.problem.comm,
                                         translate=free_obj, **more)
                Jt = T.torque_theta
                self._t_response = T.response_t
                self._theta_response = T.response_theta or None
            else:
                Jt = fe.condensed_torque_jacobian(self.solver, self.bc, ac, dsets,
                                                  self.problem.comm)
            Jl = np.zeros_like(Jt)
            h = 1e-4
            base = self.lig.torques(self.kin.motions(skel), skel, self.joints)
            for i in range(nj):
                th = self.theta.copy()
                th[i] += math.degrees(h)
                sk = self.kin.skeleton(th)
                Jl[:, i] = (self.lig.torques(self.kin.motions(sk), sk, self.joints) - base) / h
            J = Jt + Jl
            if free_obj:
                J = np.block([[J, L * T.torque_t], [L * T.force_theta, L * L * T.force_t]])
            # Newton in the coordinates q (d theta = B dq): E^T J E dq = -E^T g; a coordinate
            # is held when one of its joints sits at its limit
            Jq = E.T @ J @ E
            gq = E.T @ gx
            fq = ~np.any((E[:nj] != 0.0) & ~free[:, None], axis=0)
            dq = np.zeros(E.shape[1])
            Jf = Jq[np.ix_(fq, fq)]
            try:
                dq[fq] = np.linalg.solve(Jf, -gq[fq])
            except np.linalg.LinAlgError:
                dq[fq] = np.linalg.lstsq(Jf, -gq[fq], rcond=None)[0]
            dn = E @ dq
            # a digit that answered its last step with rho x the predicted torque change is
            # solved with rho x its tangent (slipping pad nodes give less than their stick
            # springs promise: Newton then crawled at ~6 % per iteration on the pinch's thumb);
            # each digit (and the object) moves at most its radius, damped along its soft
            # directions only, and the radii adapt to the damped step's direction (a reversal
            # = an overshoot)
            qdig = [qgroups[k] for k in np.flatnonzero(fq)]
            Kf = -np.array([rho[q] for q in qdig])[:, None] * Jf
            dq[fq] = damped_newton_step(Kf, gq[fq], qdig, limit.radius)
            dq[fq] = damped_newton_step(Kf, gq[fq], qdig, limit.update(E @ dq))
            d = limit.accept(E @ dq, dn)
            raw = float(np.degrees(np.abs(dn[:nj]).max(initial=0.0)))
            soft = ", ".join(f"{dg} x{r:.2f}" for dg, r in rho.items() if r < 0.99)
            t_now = np.array(self.contact.translation.value, dtype=float) if free_obj else None
            dt = L * d[nj:] if free_obj else np.zeros(3)
            self.say("      step (deg): " + " ".join(f"{x:+.2f}" for x in np.degrees(d[:nj]))
                     + (" object (mm): " + " ".join(f"{x:+.3f}" for x in dt) if free_obj
                        else "")
                     + f" (Newton's largest {raw:.2f}" + (f"; tangent {soft})" if soft else ")"))
            before = self.theta.copy()
            try:
                kw = {"translation": t_now + dt} if free_obj else {}
                self._go_to(self.kin.clamp(self.theta + np.degrees(d[:nj])),
                            label=f"{label}, torque iteration {it}", max_cuts=3, **kw)
            except SolverError as exc:
                return False, str(exc)
            finally:
                self._theta_response = None  # valid for this step only
            # the step taken (joint limits may have clamped it) and the change it predicted
            taken = np.radians(self.theta - before)
            if free_obj:
                taken = np.concatenate([taken, (np.array(self.contact.translation.value,
                                                         dtype=float) - t_now) / L])
            last = (gx, J @ taken)
            if uzawa and s.muscle_uzawa_rtol == 0.0 \
                    and self.contact.uzawa.penetration() > uzawa_depth_mm:
                self._one_uzawa_update(uzawa_depth_mm)
                last = None  # the update changed the residual: no response ratio from it
        return False, f"torque residual {rel:.3g} after {s.max_outer} iterations"

    def _one_uzawa_update(self, depth_mm: float) -> None:
        """One Uzawa update of the normal multipliers (penetration only, unless it is <=
        ``depth_mm``) and its re-solve."""
        self.augment(depth_mm, creep=False, max_updates=1,
                     max_depth_mm=self.wf.solver.muscle_uzawa_max_mm)

    def _friction_use(self) -> str:
        """Each participating digit's tangential / normal contact force against the friction
        coefficient: a digit at mu slides (at constant torque), and its torques cannot balance."""
        reg, _ = self.metrics()
        mu = self.grasp.friction
        parts = []
        for d in self.grasp.digits:
            fn, ft = reg[d]["normal_force_N"], reg[d]["tangential_force_N"]
            if fn <= 0.0:
                parts.append(f"{d} 0 N (off the object)")
                continue
            ratio = ft / fn
            # the patch's ratio stays a little below mu while its rim still sticks
            parts.append(f"{d} {fn:.2f} N, tangential/normal {ratio:.2f}"
                         + (" (at the friction limit)" if ratio >= 0.9 * mu else ""))
        return f"contact forces (mu = {mu:g}): " + ", ".join(parts)

    # -- outputs
    def _fields(self):
        from dolfinx import fem

        from handfe.contact import _to_p1

        mesh = self.model.mesh
        u = self.problem.displacement()
        V1 = fem.VectorFunctionSpace(mesh, ("CG", 1))
        u1 = fem.Function(V1, name="displacement")
        u1.interpolate(u)
        p1 = _to_p1(self.contact.terms.pressure, mesh, ())
        t1 = _to_p1(self.contact.terms.tangential_traction, mesh, (3,)) \
            if self.contact.terms.tangential_traction is not None else None
        return u1, p1, t1

    def _contact_node_force(self):
        """The consistent nodal contact forces (N) as a P1 vector Function: the contact
        residual at each skin node = the force the skin exerts there on the object (the sum is
        the object force of the equilibrium check). None for elements with mid-side nodes
        (the metrics then integrate the interpolated pressure)."""
        from dolfinx import fem

        from handfe.contact import assemble_nodal

        if self.problem.disc.degree != 1:
            return None
        w = fem.Function(self.problem.W)
        w.x.array[:] = assemble_nodal(self.solver.L[1])
        return w.sub(0).collapse()

    def metrics(self):
        from handfe.grasp.outputs import facet_data, region_metrics

        u1, p1, t1 = self._fields()
        self._out = (u1, p1)
        fd = facet_data(self.model, u1, p1, t1, self.obstacle, self.contact.translation.value,
                        self.wf.solver.gap_tol_mm, node_force=self._contact_node_force())
        return region_metrics(fd, self.problem.comm, self.wf.outputs.loaded_area_kPa), fd

    def report(self) -> dict[str, Any]:
        from handfe.grasp.outputs import smallest_tissue_cells

        tq = self.torque or self.torques()
        joints = {}
        for i, j in enumerate(self.joints):
            joints[j.dof] = {"measured_deg": float(self.theta_measured[i]),
                             "start_deg": float(self.kin.theta0[i]),
                             "equilibrium_deg": float(self.theta[i]),
                             "muscle_Nmm": float(tq["muscle"][i]),
                             "ligament_Nmm": float(tq["ligament"][i]),
                             "tissue_contact_Nmm": float(tq["tissue"][i]),
                             "coupling_Nmm": float(tq["coupling"][i]),
                             "residual_Nmm": float(tq["residual"][i]),
                             "relative_residual": float(tq["relative"][i]),
                             "at_limit": bool(self.at_limit[i])}
        from handfe.grasp.fe import global_equilibrium

        pen = self.contact.uzawa.penetration() if self.contact.uzawa else float("nan")
        obj = {"free": bool(getattr(self, "object_free", False)),
               "translation_mm": (np.array(self.contact.translation.value, dtype=float)
                                  - self.translation0).tolist(),
               "force_target_N": self.force_target.tolist()}
        grip = 0.0  # a held object's equilibrium error stays relative to its net force
        if obj["free"]:
            f, grip = self.object_residual()
            obj["force_residual_N"] = f.tolist()
            obj["relative_force_residual"] = float(np.linalg.norm(f) / max(grip, 1e-9))
        eq = global_equilibrium(self.solver, self.bc, self.problem.comm, scale_N=grip)
        return {"joints": joints, **eq, "object_motion": obj,
                "max_relative_torque_residual": self.max_torque_residual(tq),
                "max_penetration_mm": float(pen), "load_steps": len(self.steps),
                "newton_iterations": int(self.solver.iterations),
                "newton_stalls_accepted": int(self.solver.stalls),
                "predictor_wins": dict(self.predictor_wins),
                # Newton steps the inversion guard shortened, and the smallest fraction kept
                "guarded_steps": int(g.shortened) if (g := self.solver.guard) else 0,
                "smallest_guarded_step": float(g.smallest) if g else 1.0,
                # solver.guard_damping: the largest Levenberg-Marquardt shift used (0 = none)
                "guard_damping_max_shift": float(self.solver.damping_max),
                "final_residual_N": self._residual_norm(),
                "outer_iterations": self.outer_iterations,
                "uzawa_updates": self.augmentations, "step_cuts": self.cuts,
                # friction return mappings a failed solve dropped (scene._go_to)
                "dropped_friction_mappings": int(getattr(self, "dropped_mappings", 0)),
                "closing_deg": getattr(self, "closing_deg", {}),
                # solver.palm_force_N: the object's move into the palm before the closing
                # (direction world unit vector; travel mm; the palm's force N when it ended)
                "palm_press": getattr(self, "palm_press", None),
                # friction coefficient of the kinematic closing (muscles mode: 0 with
                # muscle_frictionless_closing; mu of the grasp otherwise)
                "closing_mu": float(getattr(self, "closing_mu", self.contact.mu)),
                "stalled_digits": self.stalled,
                "digit_force_N": getattr(self, "digit_force_N", {}),
                "penalty_N_per_mm3": float(self.contact.k_n.value),
                # J of the tissue cells: how much volume the element lets the tissue lose,
                # and where the five smallest are
                "tissue_volume": {**self.problem.tissue_volume(),
                                  "smallest_cells": smallest_tissue_cells(
                                      self.problem, self.model, self.obstacle,
                                      self.contact.translation.value)},
                "steps": self.steps}

    def write_fields(self, path: Path) -> None:
        from dolfinx import fem
        from dolfinx.io import XDMFFile

        u1, p1 = self._out
        mesh = self.model.mesh
        p1.name = "contact_pressure_MPa"
        D0 = fem.FunctionSpace(mesh, ("DG", 0))
        psi = fem.Function(D0, name="strain_energy_density_mJ_per_mm3")
        ex = fem.Expression(self.problem.skin.w_dev(self.problem.F, {
            "mu": self.problem.mu, "alpha": self.problem.alpha}),
            D0.element.interpolation_points())
        psi.interpolate(ex)
        with XDMFFile(mesh.comm, str(path), "w") as xf:
            xf.write_mesh(mesh)
            xf.write_meshtags(self.model.cell_tags)
            xf.write_function(u1)
            xf.write_function(p1)
            xf.write_function(psi)

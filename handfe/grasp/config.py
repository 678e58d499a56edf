"""Grasp definitions (``grasps/*.toml``) and run recipes (``workflows/*.toml``) as typed,
frozen dataclasses. Unknown keys and out-of-range values raise ConfigError naming file and key.

Frames: object geometry is given in the **hand frame** (origin on the distal wrist crease, x
radial, y distal, z palmar; mm), see docs/anatomy.md."""

from __future__ import annotations

import os
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from handfe.anatomy.tables import TENDON_SPLITS
from handfe.config import bounds, choices, from_dict, load, load_toml, toml_string
from handfe.errors import ConfigError
from handfe.kinematics import DIGITS
from handfe.paths import GRASPS_DIR, REPO_ROOT, WORKFLOWS_DIR

MESH_LEVELS = ("coarse", "reduced", "default", "fine")


@dataclass(frozen=True)
class ObjectSpec:
    """The rigid grasped object (mm, hand frame). ``centre_mm`` is where the placement search
    starts; the object is then moved within ``search_mm`` (half-widths along hand x, y, z) to the
    position of largest clearance to the skin of ``placement_regions`` (the grasp cavity), so the
    hand starts just short of contact."""

    shape: str = field(default="cylinder", metadata=choices("cylinder", "sphere", "capsule", "box"))
    radius_mm: float = field(default=25.0, metadata=bounds(1.0, 200.0))
    length_mm: float = field(default=120.0, metadata=bounds(1.0, 600.0))
    half_sizes_mm: tuple[float, float, float] = field(default=(20.0, 20.0, 20.0),
                                                      metadata=bounds(0.5, 300.0))
    edge_radius_mm: float = field(default=2.0, metadata=bounds(0.0, 100.0))
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    centre_mm: tuple[float, float, float] = (0.0, 90.0, 40.0)
    search_mm: tuple[float, float, float] = field(default=(0.0, 15.0, 15.0),
                                                  metadata=bounds(0.0, 100.0))
    placement_regions: tuple[str, ...] = ()
    min_clearance_mm: float = field(default=0.2, metadata=bounds(0.0, 20.0))


@dataclass(frozen=True)
class GraspSpec:
    """A grasp: posture source, participating digits, object and friction."""

    description: str = ""
    pose: str = "glove"  # "glove" = the subject's glove angles for this grasp, or a pose TOML
    digits: tuple[str, ...] = DIGITS
    friction: float = field(default=0.74, metadata=bounds(0.0, 3.0))
    # flexion (deg) taken off the measured angles of the released joints before meshing: the
    # posture "just short of contact" from which the digits close onto the object
    opening_deg: float = field(default=0.0, metadata=bounds(0.0, 90.0))
    object: ObjectSpec = field(default_factory=ObjectSpec)
    name: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        bad = [d for d in self.digits if d not in DIGITS]
        if bad or not self.digits:
            raise ConfigError(f"{self.source or '<grasp>'}: 'digits' = {list(self.digits)!r}: "
                              f"unknown digit(s) {bad} (choose from {', '.join(DIGITS)})")
        regions = set(DIGITS) | {"palm"}
        badr = [r for r in self.object.placement_regions if r not in regions]
        if badr:
            raise ConfigError(f"{self.source or '<grasp>'}: 'object.placement_regions' = "
                              f"{list(self.object.placement_regions)!r}: unknown region(s) {badr}")


@dataclass(frozen=True)
class SolverSpec:
    """Outer (joint torque balance) and inner (FE Newton) settings."""

    max_outer: int = field(default=30, metadata=bounds(1, 200))
    torque_rtol: float = field(default=1e-3, metadata=bounds(1e-8, 0.5))
    max_step_deg: float = field(default=0.5, metadata=bounds(0.1, 20.0))
    # muscles mode: the applied joint torque goes from the one holding the closed posture to
    # the muscle torque in this many load steps (halved on failure)
    muscle_steps: int = field(default=4, metadata=bounds(1, 64))
    # muscles mode: each finger's DIP flexes by dip_pip_coupling x its PIP's change (the
    # extensor mechanism / oblique retinacular ligament; 2/3 after Rijpkema & Girard 1991,
    # the default); 0 = DIP free: a finger whose pad sticks then curls (MCP+, PIP-, DIP+)
    # with the pad in place, resisted by nothing in the model (docs/grasp.md)
    dip_pip_coupling: float = field(default=2.0 / 3.0, metadata=bounds(0.0, 1.5))
    # muscles mode: true = the object translates freely (three more unknowns of the torque
    # Newton; its net contact force goes from the one the support takes in the closed posture
    # to 0 with the muscle load; rotation fixed). Default false: the object is held in space
    # and its support takes the net force, as in the source model - with the nine flexor-side
    # muscles and no extensors a free pinch has no stable posture (docs/grasp.md, run r2 of
    # 2 Dec 2026: thumb, fingers and ball travel together at every load)
    free_object: bool = False
    # muscles mode: one Uzawa update (down to step_penetration_mm) after each torque step
    # that leaves the pads deeper than that, so every balanced load is a contact, not the
    # penalty's ~1 mm at 20 N (off by default; all updates after a balanced load made a jump
    # the re-balance needed FE step cuts to 1/16 for - run r3, docs/grasp.md; with the
    # per-load friction history the coarse cylinder balanced load 0.25 at 0.1 mm, then the
    # torque steps' FE solves failed - runs U1/U2, seventeenth session)
    muscle_uzawa: bool = False
    # muscles mode: the kinematic closing runs frictionless (mu as a Constant set to 0), then
    # the stick anchors are set on the closed state and friction is switched on, so the torque
    # homotopy starts from pads that carry normal pressure only: the closing is a numerical
    # device and the shear it would build up is not data. Default since 3 Dec 2026: the coarse
    # pinch then balanced up to 0.406 of the EMG load instead of 0.1875 (docs/grasp.md)
    muscle_frictionless_closing: bool = True
    # muscles mode: before each muscle load (and the final Uzawa phase) k_n rises to the pads'
    # peak pressure x max(adaptive_penalty / facet size, 1 / step_penetration_mm), at most 2x
    # per load, with the tractions of the balanced state kept (RigidContact.stiffen), so the
    # pads do not sink in by mm under the EMG load on the closing's soft penalty.
    # Experimental, off: on the coarse cylinder an uncapped 7x stiffer k_n at load 0.5 made
    # the FE Newton of the next torque step fail through every cut (docs/grasp.md, 14th session)
    muscle_penalty_follows_pressure: bool = False
    # ... by at most this factor per load (2: 7x at once on the coarse cylinder made the next
    # torque step's FE Newton fail through every cut; the full load was then reached 1.65 mm
    # (cylinder) / 2.4 mm (ball) deep; 4 made the ball's homotopy cut its torque steps at load
    # 0.25, run SG, docs/grasp.md twenty-fourth session)
    muscle_penalty_growth: float = field(default=2.0, metadata=bounds(1.0, 100.0))
    # muscles mode: an FE solve of the torque Newton that stalls (backtracking at a contact
    # kink) at <= muscle_stall_rtol x the grip (N) is accepted, as a stall <= 1e-4 N is in
    # the closing; 0 = the closing's absolute 1e-4 N only. The reduced cylinder's final
    # contact phase stalled at 1.7-2.2e-2 N on ~126 N of grip and failed; 3e-4 let it finish
    # (cylindrical_muscles_reduced.toml, docs/grasp.md thirty-seventh session). The final
    # tight solve still makes the reported state
    muscle_stall_rtol: float = field(default=1e-4, metadata=bounds(0.0, 1e-2))
    # muscles mode: when the friction history (Coulomb return mapping: stick anchors and
    # tangential multipliers) is updated. "load" (default since 4 Dec 2026): once per
    # balanced muscle load - the torque Newton's iterations are iterations of one load step,
    # so slip is measured from the anchors of the last balanced load and the condensed FE
    # tangent is the derivative of what the next iteration sees; the coarse cylinder then
    # balanced the full EMG load to 4.8e-4 in 11 torque iterations. "iteration": after
    # every torque iteration's FE solve (before): the contact data changed between
    # iterations and the same run chattered at 3e-3 - 7e-3 (docs/grasp.md)
    muscle_friction_history: str = field(default="load", metadata=choices("load", "iteration"))
    # muscles mode, after the full EMG load: "fixed" = Uzawa updates at the fixed posture
    # until the penetration is <= penetration_tol_mm, then the torque balance again (three
    # rounds at most); on the coarse cylinder the fixed bones squeezed the pads as their depth
    # went 1.16 -> 0.5 mm, the updates failed, and the re-balance began with the thumb CMC at
    # 15x its muscle torque (docs/grasp.md, eighteenth session). "interleaved" = one Uzawa
    # update after every torque step of that balance until both hold, so the joints give way
    # as the pads harden
    muscle_final_uzawa: str = field(default="fixed", metadata=choices("fixed", "interleaved"))
    # muscles mode: an Uzawa update between torque steps (muscle_uzawa, the interleaved final
    # phase) takes at most muscle_uzawa_max_mm / penetration of the full multiplier change, so
    # the fixed-posture re-solve pushes the deepest pad out by about this much, and the torque
    # steps follow in smaller bites; 0 = full updates (docs/grasp.md, twenty-second session)
    muscle_uzawa_max_mm: float = field(default=0.0, metadata=bounds(0.0, 10.0))
    # muscles mode: an Uzawa update between torque steps waits until the relative torque
    # residual is <= muscle_uzawa_rtol, so the torque Newton catches up with the last update
    # first (and learns each digit's response ratio from consecutive steps); 0 = one after
    # every torque step. On the ball's final phase each update raised the little finger's PIP
    # residual back to ~0.33 before the next torque step, for seven updates; 0.1 let the
    # torques catch up there but still failed later, and failed the cylinder recipe's final
    # phase that passes without it (runs SQg, Qg, docs/grasp.md twenty-fourth session)
    muscle_uzawa_rtol: float = field(default=0.0, metadata=bounds(0.0, 1.0))
    # muscles mode: each torque step's FE solve may also start from the linear response of the
    # condensed tangent (dw/dtheta, the solves it needs anyway) to the step's joint angles,
    # next to the elastic extension of the bone motion and the secant predictor; the one with
    # the smallest residual is used (summary.json "predictor_wins")
    tangent_predictor: bool = False
    # before meshing, each digit closes rigidly (its released joints by one common angle, at
    # most preclose_max_deg) until its skin is preclose_clearance_mm from the object
    pre_close: bool = True
    preclose_clearance_mm: float = field(default=0.5, metadata=bounds(0.0, 20.0))
    preclose_max_deg: float = field(default=60.0, metadata=bounds(0.0, 120.0))
    # angles mode: each digit whose contact force is below digit_force_N closes its released
    # joints by closing_step_deg per load step, at most closing_deg beyond the start posture
    closing_deg: float = field(default=6.0, metadata=bounds(0.0, 45.0))
    closing_step_deg: float = field(default=0.5, metadata=bounds(0.01, 10.0))
    digit_force_N: float = field(default=5.0, metadata=bounds(0.0, 2000.0))
    # angles mode, experimental: before the digits close, the object moves into the palm
    # (along the digits' push, less the part that leaves the thumb: scene.palm_direction)
    # until the palm carries palm_force_N, in steps of at most palm_step_mm (log-force
    # secant, redone on overshoot, the digits' band digit_force_rtol) and at most
    # palm_travel_mm in all; then the digits close against it held there. 0 = the object
    # stays where it was placed (the palm takes nothing: the object's support holds the
    # digits' push; docs/grasp.md, thirty-fourth and forty-seventh sessions)
    palm_force_N: float = field(default=0.0, metadata=bounds(0.0, 2000.0))
    palm_step_mm: float = field(default=0.5, metadata=bounds(0.01, 10.0))
    palm_travel_mm: float = field(default=15.0, metadata=bounds(0.0, 60.0))
    penalty_factor: float = field(default=10.0, metadata=bounds(0.1, 1e6))
    # penalty continuation in the closing steps: k_n grows (up to max_penalty_growth x its
    # start value penalty_factor x E0/h) while a step leaves more than step_penetration_mm
    step_penetration_mm: float = field(default=0.1, metadata=bounds(1e-4, 10.0))
    max_penalty_growth: float = field(default=30.0, metadata=bounds(1.0, 1e6))
    penetration_tol_mm: float = field(default=0.01, metadata=bounds(1e-5, 1.0))
    gap_tol_mm: float = field(default=0.01, metadata=bounds(0.0, 1.0))
    max_augment: int = field(default=12, metadata=bounds(0, 100))
    # contact scheme (docs/contact.md): adaptive_penalty c > 0 lets k_n follow c x p_peak / h
    # after each Uzawa update (0 = off); augmented_friction puts the stick traction in
    # tangential multipliers with a stick spring stick_ratio x k_n
    adaptive_penalty: float = field(default=0.0, metadata=bounds(0.0, 1e4))
    augmented_friction: bool = False
    stick_ratio: float = field(default=1.0, metadata=bounds(0.01, 1.0))
    stick_tol_mm: float = field(default=0.02, metadata=bounds(1e-5, 1.0))
    # the Coulomb cone rounded over (1 +- friction_smoothing) mu p (handfe.contact.smoothed_cone:
    # a continuous tangent where points sit on the cone; at most friction_smoothing/4 x mu p
    # less friction there); 0 = the sharp cone
    friction_smoothing: float = field(default=0.0, metadata=bounds(0.0, 0.5))
    # Newton tolerance (N, residual norm) of the closing steps and their Uzawa updates (2e-3 x
    # the digit forces, at most this); then a tight solve (1e-9 N, a stall <= 1e-4 N accepted)
    # and the final Uzawa phase, tight too, make the reported state. 0 = every solve tight.
    # Newton on the contact kinks stalls at 1e-4..1e-2 N, i.e. 2e-5..2e-3 of a 5 N digit
    # force, and a stalled closing step was cut down to 1/128 (docs/grasp.md, tenth session)
    closing_atol_N: float = field(default=0.0, metadata=bounds(0.0, 0.1))
    # Newton line search tried first ("bt" backtracking or "basic" full steps); the other is
    # the fallback before a step is cut
    # closing steps: Uzawa updates after each step until its penetration is <=
    # step_penetration_mm (the multipliers carry the pads' load; k_n stays soft) instead of
    # only raising the penalty
    step_uzawa: bool = False
    # angles mode: closing_secant sizes each digit's next step from its last two (angle, force)
    # pairs (log-force secant aimed just under digit_force_N or at 3x the digit's force,
    # whichever is smaller; at most closing_step_deg) and redoes a step that overshoots; a
    # digit stops once its force is >= (1 - digit_force_rtol) x digit_force_N. The band is the
    # closing's, not the result's: the other digits' closing and the final Uzawa phase move a
    # stopped digit's force (coarse pinch at rtol 0.02: -5 to +27 % off; docs/grasp.md)
    closing_secant: bool = False
    digit_force_rtol: float = field(default=0.0, metadata=bounds(0.0, 0.9))
    # contact facet quadrature: "vertex" collocates the contact force at the nodes, where the
    # Uzawa update enforces the gap (P1 elements only; docs/contact.md); "gauss" = 2nd order
    contact_quadrature: str = field(default="gauss", metadata=choices("gauss", "vertex"))
    newton_linesearch: str = field(default="bt", metadata=choices("bt", "basic"))
    # fraction-to-the-boundary rule on J = det F (handfe.step_guard): every Newton step is
    # shortened so that no cell's J drops below inversion_guard x its value at the iterate
    # (full steps at a stiff loaded contact inverted cells: NaN residual, SNES -4). 0 = off
    inversion_guard: float = field(default=0.0, metadata=bounds(0.0, 0.9))
    # with inversion_guard: once the guard cuts a Newton step below 0.1 of its length, the
    # next Jacobians add lambda |K_ii| to the displacement diagonal (Levenberg-Marquardt:
    # lambda 1e-3, x10 after each such step, /10 after a step the guard left whole, 0 below
    # 1e-3). The residual is unchanged, so is a converged state; the damped steps avoid the
    # near-singular modes that drive cells to collapse (reduced muscle-driven cylinder: load
    # 0.25 balanced without a failed solve where it had failed through four cuts, the full
    # load in 27 min; docs/grasp.md, thirty-sixth session; cylindrical_muscles_reduced.toml)
    guard_damping: bool = False
    # line search of the re-solves after a change of the contact data (Uzawa update, penalty
    # increase) from a converged state; "basic" falls back to "bt" from that state
    resolve_linesearch: str = field(default="bt", metadata=choices("bt", "basic"))
    # augmented friction: the share of the stick data's change (tangential multipliers and
    # anchors) a full Uzawa update takes. Below 1 the due friction return mapping (itself
    # lambda_t <- t_T) is the update's tangential step, not followed by a second
    # lambda_t <- t_T, and the change is under-relaxed; the normal update stays full. 1 = the
    # full change, mapping and second update both (as before 6 Dec 2026). On the reduced
    # cylinder the first update after a closing step crawled (11-33 Newton iterations) at 1,
    # 3-12 at 0.5 (docs/grasp.md, thirty-third session)
    uzawa_tangential_relax: float = field(default=1.0, metadata=bounds(0.05, 1.0))
    nu: float = field(default=0.49, metadata=bounds(0.3, 0.49999))
    # shear modulus in the p1-p1s stabilisation beta h^2 / (2 mu) |grad p|^2: "tangent" = each
    # cell's incremental modulus at the last converged state (lagged); "initial" = the
    # small-strain mu0 (0.6-1.2 kPa), the default until 5 Dec 2026: against a Taylor-Hood run of
    # the coarse pinch its pads had about half the contact area and 31-73 % higher peaks,
    # "tangent" -31..+3 % and -6..+11 % (docs/grasp.md, twenty-fifth session); "pressure" =
    # the tangent one but at least stabilisation_pressure_factor x |p| (the cell's mean
    # pressure). Other elements have no such term: the default is ignored there, a value
    # written in the workflow is refused
    stabilisation_modulus: str = field(default="tangent", metadata=choices("initial",
                                                                          "tangent",
                                                                          "pressure"))
    stabilisation_pressure_factor: float = field(default=10.0, metadata=bounds(0.1, 1000.0))


@dataclass(frozen=True)
class Outputs:
    fields: bool = True
    png: bool = True
    # regions.csv loaded_area_mm2: skin with nodal contact pressure >= this (kPa)
    loaded_area_kPa: float = field(default=10.0, metadata=bounds(0.1, 1000.0))


@dataclass(frozen=True)
class Workflow:
    """A run recipe: subject + grasp + loading + mesh level + outputs."""

    subject: str = "subjects/S01"
    grasp: str = "cylindrical"  # a name in grasps/ or a path to a grasp TOML
    trial: int = field(default=0, metadata=bounds(0, 1000))  # 0 = mean over the trials
    # "angles" (kinematic closing) by default: the muscle-driven mode does not converge yet
    loading: str = field(default="angles", metadata=choices("muscles", "angles"))
    # muscles mode: every muscle force x this (1 = the subject's EMG estimate for the grasp;
    # below 1 a lighter grip, the EMG-to-force map being linear). At 0.1 the pinch and the
    # ball run to the end at coarse, where the full load fails (docs/grasp.md, thirty-ninth
    # session; workflows/*_muscles_light.toml); the angles mode does not use it
    muscle_force_scale: float = field(default=1.0, metadata=bounds(0.01, 2.0))
    # muscles mode: how FDS's and FDP's forces split between digits 2-5. "equal" (1/4 each,
    # anatomy/insertions.csv); "holzbaur2005": in proportion to each compartment's peak
    # isometric force (little finger FDS 0.11, FDP 0.29; anatomy/tendon_splits.csv). Written
    # only in a muscles-mode workflow (refused in the angles mode, whatever its value)
    tendon_split: str = field(default="equal", metadata=choices(*TENDON_SPLITS))
    mesh: str = field(default="reduced", metadata=choices(*MESH_LEVELS))
    # p1-p1s: P1-P1 u-p with pressure stabilisation (locking-free, default); p1-p0: the hybrid
    # linear tet (locks on tets, see docs/grasp.md); taylor-hood: P2-P1 (reference, ~8x dofs)
    element: str = field(default="p1-p1s", metadata=choices("p1-p1s", "p1-p0", "taylor-hood"))
    solver: SolverSpec = field(default_factory=SolverSpec)
    outputs: Outputs = field(default_factory=Outputs)
    source: str = ""

    def subject_dir(self) -> Path:
        p = _resolve(self.subject, self.source)
        if not (p / "anthropometry.toml").is_file():
            raise ConfigError(f"{self.source or '<workflow>'}: 'subject' = {self.subject!r}: no "
                              f"subject folder with anthropometry.toml at {p}")
        return p

    def grasp_spec(self) -> GraspSpec:
        g = self.grasp
        p = GRASPS_DIR / f"{g}.toml" if "/" not in g and not g.endswith(".toml") \
            else _resolve(g, self.source)
        if not p.is_file():
            known = ", ".join(sorted(q.stem for q in GRASPS_DIR.glob("*.toml")))
            raise ConfigError(f"{self.source or '<workflow>'}: 'grasp' = {g!r}: no grasp file "
                              f"{p} (grasps/: {known})")
        spec = load(GraspSpec, p)
        return replace(spec, name=spec.name or p.stem, source=str(p))


def _resolve(path: str, source: str) -> Path:
    p = Path(path)
    if p.is_absolute():
        return p
    if (REPO_ROOT / p).exists() or not source:
        return REPO_ROOT / p
    return Path(source).parent / p


def load_workflow(path: str | Path, overrides: dict | None = None) -> Workflow:
    """Read a workflow TOML (path, or a name in workflows/).

    A workflow may start from another one: ``base = "cylindrical_muscles"`` (a name in
    workflows/, or a path relative to this file or to the repository) takes every key of that
    workflow (itself checked as a workflow first) and this file's keys over it, table by table
    (``[solver]`` keys one by one), so a variant states only what it changes. ``overrides``
    (:func:`parse_overrides`, ``handfe run --set``) go over the file's keys the same way."""
    return _load_workflow(_workflow_path(path), (), overrides)[0]


def parse_overrides(items: list[str] | tuple[str, ...], *, source: str = "--set") -> dict:
    """``["solver.guard_damping=true", "mesh=coarse", ...]`` as a workflow table (values read
    as TOML, a bare word as a string), each key checked against the workflow's keys and
    ranges; an error names ``source`` and the item."""
    table: dict = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            raise ConfigError(f"{source} {item!r}: expected KEY=VALUE, e.g. "
                              "solver.guard_damping=true")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        *tables, leaf = key.split(".")
        node = table
        for t in tables:
            node = node.setdefault(t, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{source} {item!r}: '{t}' is not a table")
        node[leaf] = value
    from_dict(Workflow, table, source=source)
    return table


def muscles_only_settings(wf: Workflow) -> list[str]:
    """The settings of ``wf`` that act in the muscles mode only and differ from their defaults
    (a run in the angles mode would drop them without a word)."""
    out = []
    if wf.muscle_force_scale != 1.0:
        out.append(f"muscle_force_scale = {wf.muscle_force_scale:g}")
    if wf.tendon_split != "equal":
        out.append(f"tendon_split = {wf.tendon_split!r}")
    if wf.solver.free_object:
        out.append("solver.free_object = true")
    return out


def angles_only_settings(wf: Workflow) -> list[str]:
    """The settings of ``wf`` that act in the angles mode only and differ from their defaults
    (the muscles mode would drop them without a word)."""
    return [f"solver.palm_force_N = {wf.solver.palm_force_N:g}"] \
        if wf.solver.palm_force_N > 0.0 else []


def _load_workflow(p: Path, chain: tuple[Path, ...],
                   overrides: dict | None = None) -> tuple[Workflow, dict]:
    """The workflow in file ``p`` and its keys merged over its bases'; ``chain``: the files
    that use it as a base, innermost last; ``overrides`` (:func:`parse_overrides`) over all."""
    raw = _merge(_workflow_raw(p, chain), overrides or {})
    # an error of the keys together names the overrides too: they may be its cause
    src = f"{p} with --set" if overrides else str(p)
    wf = replace(from_dict(Workflow, raw, source=src), source=str(p))
    # the key as written (the default applies to p1-p1s only and is not refused elsewhere)
    given = raw.get("solver", {}).get("stabilisation_modulus")
    if given is not None and wf.element != "p1-p1s":
        raise ConfigError(f"{src}: 'solver.stabilisation_modulus' = {given!r} stabilises the "
                          f"p1-p1s element; element = {wf.element!r} has no such term")
    # the keys as written (as stabilisation_modulus above): a default is not a mistake in the
    # angles mode, a muscle key written into an angles workflow is, whatever its value
    for key in ("muscle_force_scale", "tendon_split"):
        given = raw.get(key)
        if given is not None and wf.loading != "muscles":
            raise ConfigError(f"{src}: {key!r} = {given!r} sets the muscles mode's loads; "
                              f"loading = {wf.loading!r} does not use them")
    # the angles mode closes each digit against the object where it is held: a free object
    # there would be a held one without a word
    if wf.solver.free_object and wf.loading != "muscles":
        raise ConfigError(f"{src}: 'solver.free_object' = true frees the object in the muscles "
                          f"mode only; loading = {wf.loading!r} closes each digit to its "
                          "force against the object held in place")
    if wf.solver.palm_force_N > 0.0 and wf.loading == "muscles":
        raise ConfigError(f"{src}: 'solver.palm_force_N' = {wf.solver.palm_force_N:g} presses "
                          "the object into the palm before the kinematic closing (loading = "
                          "'angles'); in the muscles mode the palm takes the push with "
                          "'solver.free_object' = true")
    if wf.solver.guard_damping and wf.solver.inversion_guard <= 0.0:
        raise ConfigError(f"{src}: 'solver.guard_damping' = true needs 'solver.inversion_guard' "
                          f"> 0 (it is {wf.solver.inversion_guard:g}): the damping follows "
                          "the guard's step cuts")
    wf.subject_dir()
    wf.grasp_spec()
    return wf, raw


def _workflow_path(path: str | Path, source: Path | None = None) -> Path:
    """A workflow file: ``path`` (for a base of ``source``: relative to ``source``'s folder
    first, then to the repository), else a name in workflows/."""
    p = Path(path)
    if p.is_absolute():
        return p
    roots = (source.parent, REPO_ROOT) if source is not None else ()
    for q in (*(r / p for r in roots), p):
        if q.is_file():
            return q
    return WORKFLOWS_DIR / f"{path}.toml" if not p.suffix else p


def _workflow_raw(p: Path, chain: tuple[Path, ...]) -> dict:
    """The keys of workflow file ``p`` over those of its ``base`` chain (each base loaded and
    checked as a workflow on its own, so an error names the file it is in)."""
    raw = load_toml(p)
    base = raw.pop("base", None)
    if base is None:
        return raw
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{p}: 'base' = {base!r}: expected a workflow name or path")
    bp = _workflow_path(base, p)
    if not bp.is_file():
        known = ", ".join(sorted(q.stem for q in WORKFLOWS_DIR.glob("*.toml")))
        raise ConfigError(f"{p}: 'base' = {base!r}: no workflow file {bp} (workflows/: {known})")
    seen = (*chain, p.resolve())
    if bp.resolve() in seen:
        loop = " -> ".join(str(q) for q in (*seen, bp.resolve()))
        raise ConfigError(f"{p}: 'base' = {base!r}: the bases form a loop ({loop})")
    merged = dict(_load_workflow(bp, seen)[1])
    for key in ("subject", "grasp"):
        # a base's relative path means the same folder when another file uses it
        v = merged.get(key)
        path_like = key == "subject" or "/" in str(v) or str(v).endswith(".toml")
        if key not in raw and isinstance(v, str) and path_like \
                and _resolve(v, str(bp)) != _resolve(v, str(p)):
            merged[key] = os.path.normpath(_resolve(v, str(bp)))
    return _merge(merged, raw)


def _merge(under: dict, over: dict) -> dict:
    """``over``'s keys over ``under``'s, tables key by key."""
    out = dict(under)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = {**out[key], **value}
        else:
            out[key] = value
    return out


def workflow_toml(wf: Workflow) -> str:
    """Every key of ``wf`` as a workflow TOML (``handfe run --show``): what a run of it uses,
    after its base and any ``--set``; loading the text gives ``wf`` back."""

    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return toml_string(v)
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    d = asdict(wf)
    lines = [f"# every key of {wf.source or 'the workflow'} (its base and --set applied)"]
    lines += [f"{k} = {value(v)}" for k, v in d.items() if not isinstance(v, dict)
              and k != "source"]
    for table in ("solver", "outputs"):
        lines += ["", f"[{table}]"] + [f"{k} = {value(v)}" for k, v in d[table].items()]
    return "\n".join(lines) + "\n"

"""Sensitivity study definitions (``sensitivity/*.toml``) as frozen dataclasses.

A study names a baseline (a grasp workflow, or the layered fingertip scene for quick runs), the
parameters perturbed one at a time, the levels (% of the baseline value) and the outputs
(regions x metrics). See docs/sensitivity.md for the file format and an example.
"""

from __future__ import annotations

import csv
import hashlib
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from handfe.config import bounds, choices, from_dict, load_toml
from handfe.errors import ConfigError
from handfe.paths import REFERENCE_DIR, REPO_ROOT

MATERIAL_PARAMETERS = ("skin", "subcutaneous")
LOAD_PARAMETERS_FINGERTIP = ("force",)
METRICS = {
    "grasp": ("contact_area_mm2", "loaded_area_mm2", "mean_pressure_kPa", "peak_pressure_kPa",
              "normal_force_N", "tangential_force_N"),
    "fingertip": ("contact_area_mm2", "mean_pressure_kPa", "peak_pressure_kPa", "deflection_mm"),
}
DEFAULT_REGIONS = {"grasp": ("thumb", "index", "middle", "ring", "little", "palm"),
                   "fingertip": ("pad",)}


def known_muscles() -> tuple[str, ...]:
    """Muscle names of reference/muscle_forces_by_grasp.csv (FDS, FDP, APL, APB, AP, FPB, ...)."""
    with (REFERENCE_DIR / "muscle_forces_by_grasp.csv").open() as fh:
        return tuple(r["muscle"] for r in csv.DictReader(fh))


@dataclass(frozen=True)
class RefitSettings:
    """Material refit (handfe.sensitivity.refit): stretch ranges (-), points, starts, limits."""

    fit_stretch: tuple[float, float] = field(default=(0.6, 1.5), metadata=bounds(0.1, 5.0))
    n_points: int = field(default=46, metadata=bounds(8, 1000))
    n_starts: int = field(default=6, metadata=bounds(1, 50))
    stability_stretch: tuple[float, float] = field(default=(0.5, 2.0), metadata=bounds(0.05, 10))
    max_fit_error_pct: float = field(default=1.0, metadata=bounds(0.0, 100.0, lo_open=True))
    #: what to do with a refit that is Drucker-unstable or fits poorly: "skip" = record the case
    #: as skipped (not run), "run" = run it and flag it in every table
    policy: str = field(default="skip", metadata=choices("skip", "run"))
    #: Poisson's ratio of the tissue sets (all cases, baseline included)
    tissue_nu: float = field(default=0.49, metadata=bounds(0.3, 0.5, hi_open=True))


@dataclass(frozen=True)
class FingertipSettings:
    """Layered fingertip scene (kind = "fingertip"): plate force (N), angle (deg), mesh."""

    force_N: float = field(default=1.0, metadata=bounds(0.0, 20.0, lo_open=True))
    angle_deg: float = field(default=15.0, metadata=bounds(0.0, 90.0))
    mesh: str = "reduced"
    h_mm: float | None = field(default=None, metadata=bounds(0.2, 5.0))
    skin_thickness_mm: float = field(default=1.0, metadata=bounds(0.2, 3.0))
    friction: float = field(default=0.74, metadata=bounds(0.0, 5.0))
    #: relative tolerance on the plate force (force control, secant refinement)
    force_rtol: float = field(default=0.005, metadata=bounds(1e-4, 0.1))
    element: str = field(default="taylor-hood",
                         metadata=choices("taylor-hood", "p2", "p1", "p1-p0"))


@dataclass(frozen=True)
class Study:
    """One sensitivity study. ``levels_pct`` applies to every parameter unless
    ``levels_by_parameter`` gives that parameter its own list."""

    name: str
    kind: str = field(metadata=choices("grasp", "fingertip"))
    parameters: tuple[str, ...]
    levels_pct: tuple[float, ...] = (-20.0, -10.0, -5.0, 5.0, 10.0, 20.0)
    levels_by_parameter: dict[str, tuple[float, ...]] = field(default_factory=dict)
    metrics: tuple[str, ...] = ()
    regions: tuple[str, ...] = ()
    workflow: str = ""
    #: grasp studies: the loading mode of every case ("muscles" / "angles"); None = the
    #: workflow's. Muscle-force parameters need "muscles" (the angles mode ignores them).
    loading: str | None = field(default=None, metadata=choices("muscles", "angles"))
    mesh: str | None = None
    description: str = ""
    refit: RefitSettings = field(default_factory=RefitSettings)
    fingertip: FingertipSettings = field(default_factory=FingertipSettings)
    #: where the file came from (set by :func:`load_study`, not a TOML key)
    source: str = field(default="<dict>", metadata={"internal": True})

    def __post_init__(self) -> None:
        src = self.source
        if not self.name or not all(c.isalnum() or c in "-_." for c in self.name):
            raise ConfigError(f"{src}: 'name' = {self.name!r}: use letters, digits, - _ .")
        if not self.parameters:
            raise ConfigError(f"{src}: 'parameters' is empty: name at least one parameter")
        if len(set(self.parameters)) != len(self.parameters):
            raise ConfigError(f"{src}: 'parameters' = {list(self.parameters)}: duplicates")
        allowed = self.allowed_parameters()
        for i, p in enumerate(self.parameters):
            if p not in allowed:
                raise ConfigError(f"{src}: 'parameters[{i}]' = {p!r}: unknown parameter for kind "
                                  f"'{self.kind}' (allowed: {', '.join(allowed)})")
        for k in self.levels_by_parameter:
            if k not in self.parameters:
                raise ConfigError(f"{src}: 'levels_by_parameter.{k}': {k!r} is not in "
                                  "'parameters'")
        for p in self.parameters:
            key = (f"levels_by_parameter.{p}" if p in self.levels_by_parameter else "levels_pct")
            lv = self.levels(p)
            if not lv:
                raise ConfigError(f"{src}: '{key}' is empty")
            for v in lv:
                if not math.isfinite(v) or v == 0.0 or not -90.0 <= v <= 500.0:
                    raise ConfigError(f"{src}: '{key}' = {list(lv)}: level {v:g} % must be "
                                      "non-zero and within -90..500 %")
            if len(set(lv)) != len(lv):
                raise ConfigError(f"{src}: '{key}' = {list(lv)}: duplicate levels")
        for name in ("fit_stretch", "stability_stretch"):
            lo, hi = getattr(self.refit, name)
            if not lo < hi:
                raise ConfigError(f"{src}: 'refit.{name}' = [{lo:g}, {hi:g}]: need lo < hi")
        ok_metrics = METRICS[self.kind]
        for i, m in enumerate(self.metrics):
            if m not in ok_metrics:
                raise ConfigError(f"{src}: 'metrics[{i}]' = {m!r}: unknown metric for kind "
                                  f"'{self.kind}' (allowed: {', '.join(ok_metrics)})")
        if not self.metrics:
            object.__setattr__(self, "metrics", ok_metrics)
        if not self.regions:
            object.__setattr__(self, "regions", DEFAULT_REGIONS[self.kind])
        if self.kind == "grasp":
            if not self.workflow:
                raise ConfigError(f"{src}: missing 'workflow' (the baseline grasp workflow "
                                  "TOML) for kind = 'grasp'")
            if self.workflow_path() is None:
                raise ConfigError(f"{src}: 'workflow' = {self.workflow!r}: file not found "
                                  f"(looked next to the study file and under {REPO_ROOT})")
            self._check_muscles_act()
        elif self.workflow:
            raise ConfigError(f"{src}: 'workflow' = {self.workflow!r}: only for kind = 'grasp'")
        elif self.loading is not None:
            raise ConfigError(f"{src}: 'loading' = {self.loading!r}: only for kind = 'grasp'")
        if self.kind == "fingertip" and tuple(self.regions) != ("pad",):
            raise ConfigError(f"{src}: 'regions' = {list(self.regions)}: the fingertip scene "
                              "has one region, 'pad'")

    def baseline_loading(self) -> str:
        """The loading mode the grasp cases run with: ``loading``, else the workflow's."""
        if self.loading is not None:
            return self.loading
        from handfe.grasp.config import load_workflow

        return load_workflow(self.workflow_path()).loading

    def _check_muscles_act(self) -> None:
        """A muscle-force parameter with kinematic loading would give every case the
        baseline's numbers (the angles mode closes each digit to a set force and never reads
        the muscle forces): refused instead of tabulating zero changes."""
        muscles = [(i, p) for i, p in enumerate(self.parameters) if p not in MATERIAL_PARAMETERS]
        if not muscles or self.baseline_loading() == "muscles":
            return
        i, p = muscles[0]
        where = ("'loading' = 'angles'" if self.loading is not None else
                 f"its workflow {self.workflow!r} has loading = 'angles'")
        raise ConfigError(
            f"{self.source}: 'parameters[{i}]' = {p!r}: a muscle force only acts with "
            f"loading = 'muscles', and {where} (digits closed to a set force: every {p} case "
            "would equal the baseline). Set loading = \"muscles\" in the study, or perturb "
            "only the materials")

    def allowed_parameters(self) -> tuple[str, ...]:
        if self.kind == "grasp":
            return MATERIAL_PARAMETERS + known_muscles()
        return MATERIAL_PARAMETERS + LOAD_PARAMETERS_FINGERTIP

    def levels(self, parameter: str) -> tuple[float, ...]:
        """Levels (%) of ``parameter``, sorted ascending."""
        return tuple(sorted(self.levels_by_parameter.get(parameter, self.levels_pct)))

    def workflow_path(self) -> Path | None:
        """The baseline workflow file: absolute, else next to the study file, else under the
        repository root; None if not found."""
        p = Path(self.workflow)
        cands = [p] if p.is_absolute() else [Path(self.source).parent / p, REPO_ROOT / p]
        for c in cands:
            if c.is_file():
                return c.resolve()
        return None

    def workflow_digest(self) -> str:
        wp = self.workflow_path()
        return hashlib.sha256(wp.read_bytes()).hexdigest()[:16] if wp else ""

    def with_mesh(self, mesh: str | None) -> Study:
        """The study with a mesh level override (CLI --mesh); for the fingertip kind this sets
        the scene's mesh level and drops its h_mm."""
        if mesh is None:
            return self
        if self.kind == "fingertip":
            return replace(self, mesh=mesh, fingertip=replace(self.fingertip, mesh=mesh,
                                                              h_mm=None))
        return replace(self, mesh=mesh)


def study_from_dict(data: dict, *, source: str = "<dict>") -> Study:
    if "source" in data:
        raise ConfigError(f"{source}: unknown key 'source'")
    return from_dict(Study, {**data, "source": source}, source=source)


def load_study(path: str | Path) -> Study:
    """Read and check a study TOML; problems raise ConfigError naming file, key and value."""
    return study_from_dict(load_toml(path), source=str(path))

"""Joint degrees of freedom and hand postures.

The 27 DOF, their limits and sign conventions are data: ``anatomy/joints.csv``. A :class:`Pose`
holds a value per DOF (degrees for rotations, mm for translations); DOFs it does not name are at
their neutral value. Forward kinematics (bone frames from a pose) lives in :mod:`handfe.anatomy`,
which knows the bone lengths.

Glove processing (:func:`grasp_angles`, :func:`grasp_pose`): a subject's glove recordings, raw
sensor counts through a linear calibration or already in degrees, become the 27 DOF; every sample
is checked against the joint limits; the hold-window mean of each trial is averaged over trials.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from handfe.config import choices, load_toml, toml_string
from handfe.errors import InputError
from handfe.paths import ANATOMY_DIR

DIGITS = ("thumb", "index", "middle", "ring", "little")


@dataclass(frozen=True)
class Dof:
    """One degree of freedom: rotation (deg) or translation (mm) with its limits."""

    name: str
    joint: str
    digit: str
    kind: str  # "rotation" | "translation"
    axis: str
    unit: str  # "deg" | "mm"
    min: float
    max: float
    neutral: float


def _read_joint_table(path: Path) -> dict[str, Dof]:
    with path.open() as fh:
        rows = csv.DictReader(line for line in fh if not line.startswith("#"))
        table = {}
        for r in rows:
            d = Dof(r["dof"], r["joint"], r["digit"], r["kind"], r["axis"], r["unit"],
                    float(r["min"]), float(r["max"]), float(r["neutral"]))
            table[d.name] = d
    return table


@lru_cache(maxsize=4)
def joint_table(path: str | None = None) -> dict[str, Dof]:
    """The DOF table (default ``anatomy/joints.csv``), keyed by DOF name, in file order."""
    return _read_joint_table(Path(path) if path else ANATOMY_DIR / "joints.csv")


@dataclass(frozen=True)
class Pose:
    """Joint values by DOF name (deg / mm). Unnamed DOFs are neutral. Validated on construction:
    an unknown DOF or a value outside its limits raises :class:`InputError` naming both."""

    values: Mapping[str, float] = field(default_factory=dict)
    source: str = "<pose>"

    def __post_init__(self) -> None:
        table = joint_table()
        for name, v in self.values.items():
            if name not in table:
                raise InputError(f"{self.source}: unknown joint DOF '{name}' "
                                 f"(see anatomy/joints.csv)")
            d = table[name]
            if not (d.min <= float(v) <= d.max):
                raise InputError(f"{self.source}: {name} = {v:g} {d.unit} is outside the joint "
                                 f"limits [{d.min:g}, {d.max:g}] {d.unit}")
        object.__setattr__(self, "values", {k: float(v) for k, v in self.values.items()})

    def __getitem__(self, name: str) -> float:
        table = joint_table()
        if name not in table:
            raise KeyError(name)
        return self.values.get(name, table[name].neutral)

    def as_dict(self) -> dict[str, float]:
        """All 27 DOF values, in table order."""
        return {name: self[name] for name in joint_table()}

    @classmethod
    def neutral(cls) -> Pose:
        return cls({})

    @classmethod
    def from_toml(cls, path: str | Path) -> Pose:
        """A TOML file with a table ``[angles]`` of DOF = value (deg or mm)."""
        data = load_toml(path)
        unknown = set(data) - {"angles", "description"}
        if unknown:
            raise InputError(f"{path}: unknown key '{sorted(unknown)[0]}' (allowed: angles, "
                             "description)")
        angles = data.get("angles", {})
        for k, v in angles.items():
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise InputError(f"{path}: angles.{k} = {v!r}: expected a number")
        return cls(angles, source=str(path))

    def to_toml(self, description: str = "") -> str:
        """TOML text that :meth:`from_toml` reads back (all 27 DOFs, table order)."""
        lines = []
        if description:
            lines.append(f"description = {toml_string(description)}")
        lines.append("")
        lines.append("[angles]  # deg for rotations, mm for translations (anatomy/joints.csv)")
        lines += [f"{k} = {v:.3f}" for k, v in self.as_dict().items()]
        return "\n".join(lines) + "\n"

    def write_toml(self, path: str | Path, description: str = "") -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_toml(description))
        return p


# ----------------------------------------------------------------------------- data glove
# Glove recordings -> the 27 DOF (brief S1: "a data glove measures the joint angles"). Formats:
# subjects/README.md. Rotations in deg; DOFs the glove does not see stay at their neutral value.

@dataclass(frozen=True)
class GloveSettings:
    """Table ``[glove]`` of a subject's ``trials.toml``.

    ``format = "angles"``: glove CSVs hold ``time_s`` and DOF columns in degrees (already
    calibrated). ``format = "raw"``: sensor columns (counts) and a linear ``calibration`` file.
    """

    format: str = field(default="raw", metadata=choices("raw", "angles"))
    calibration: str = ""


@dataclass(frozen=True)
class GloveCalibration:
    """Linear calibration angle_deg = gain @ counts + offset_deg (cross-coupled sensors allowed).

    ``gain`` has one row per DOF in ``dofs`` and one column per sensor in ``sensors``."""

    source: str
    dofs: tuple[str, ...]
    sensors: tuple[str, ...]
    gain: np.ndarray
    offset_deg: np.ndarray

    def apply(self, counts: Mapping[str, np.ndarray], source: str = "") -> dict[str, np.ndarray]:
        """DOF -> angle trace (deg) from sensor traces; a missing sensor is an error naming it."""
        missing = [s for s in self.sensors if s not in counts]
        if missing:
            raise InputError(f"{source or '<glove>'}: sensor '{missing[0]}' used by the "
                             f"calibration {self.source} is missing from the file")
        x = np.vstack([np.asarray(counts[s], dtype=float) for s in self.sensors])
        ang = self.gain @ x + self.offset_deg[:, None]
        return {d: ang[i] for i, d in enumerate(self.dofs)}


def read_glove_calibration(path: str | Path) -> GloveCalibration:
    """Long-form CSV ``dof,sensor,gain``: angle(dof) = sum of gain * counts(sensor) over its
    rows; the pseudo-sensor ``offset`` gives the constant term in degrees."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: glove calibration file not found")
    table = joint_table()
    terms: dict[str, dict[str, float]] = {}
    with p.open() as fh:
        rows = csv.DictReader(line for line in fh if line.strip() and not line.startswith("#"))
        if rows.fieldnames is None or not {"dof", "sensor", "gain"} <= set(rows.fieldnames):
            raise InputError(f"{p}: needs the columns dof, sensor, gain")
        for i, r in enumerate(rows, start=1):
            dof, sensor = r["dof"].strip(), r["sensor"].strip()
            if dof not in table:
                raise InputError(f"{p}, row {i}: unknown joint DOF '{dof}' (see "
                                 "anatomy/joints.csv)")
            try:
                g = float(r["gain"])
            except (TypeError, ValueError):
                raise InputError(f"{p}, row {i}: gain '{r['gain']}' is not a number") from None
            if not np.isfinite(g):
                raise InputError(f"{p}, row {i}: gain '{r['gain']}' is not finite")
            if sensor in terms.setdefault(dof, {}):
                raise InputError(f"{p}, row {i}: {dof}/{sensor} given twice")
            terms[dof][sensor] = g
    if not terms:
        raise InputError(f"{p}: no calibration rows")
    dofs = tuple(d for d in table if d in terms)
    sensors = tuple(dict.fromkeys(s for d in dofs for s in terms[d] if s != "offset"))
    gain = np.array([[terms[d].get(s, 0.0) for s in sensors] for d in dofs])
    offset = np.array([terms[d].get("offset", 0.0) for d in dofs])
    return GloveCalibration(str(p), dofs, sensors, gain, offset)


def check_joint_limits(angles: Mapping[str, np.ndarray], time: np.ndarray,
                       source: str) -> None:
    """Raise :class:`InputError` at the first sample of any DOF outside its joint limits, naming
    the file, DOF, time, value and limits."""
    table = joint_table()
    for dof, x in angles.items():
        d = table[dof]
        bad = (x < d.min) | (x > d.max) | ~np.isfinite(x)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{source}: {dof} = {x[i]:.1f} {d.unit} at t = {time[i]:.3f} s is "
                             f"outside the joint limits [{d.min:g}, {d.max:g}] {d.unit} "
                             f"(anatomy/joints.csv); check the glove calibration")


def glove_angles(path: str | Path, settings: GloveSettings,
                 calibration: GloveCalibration | None = None) -> tuple[np.ndarray, dict]:
    """Time (s) and DOF -> angle trace (deg) of one glove recording, limits checked over the
    whole recording."""
    from handfe.emg import read_timeseries

    ts = read_timeseries(path)
    if settings.format == "angles":
        table = joint_table()
        unknown = [c for c in ts.columns if c not in table]
        if unknown:
            raise InputError(f"{ts.path}: column '{unknown[0]}' is not a joint DOF of "
                             "anatomy/joints.csv (format = 'angles')")
        angles = {d: np.asarray(ts.columns[d], dtype=float) for d in table if d in ts.columns}
    else:
        if calibration is None:
            raise InputError(f"{ts.path}: raw glove data needs a calibration file "
                             "([glove] calibration in trials.toml)")
        angles = calibration.apply(ts.columns, str(ts.path))
    check_joint_limits(angles, ts.time, str(ts.path))
    return ts.time, angles


@dataclass(frozen=True)
class GraspAngles:
    """Joint angles of a grasp: per-trial hold means and mean/SD over trials (deg / mm)."""

    subject_id: str
    grasp: str
    source: str
    measured: tuple[str, ...]
    trials: tuple[tuple[int, tuple[float, float], dict[str, float]], ...]  # (trial, hold, angles)

    def mean_sd(self) -> dict[str, tuple[float, float]]:
        """All 27 DOFs -> (mean, sample SD) over trials; unmeasured DOFs: (neutral, 0)."""
        out = {}
        for name, d in joint_table().items():
            if name in self.measured:
                v = np.array([a[name] for _, _, a in self.trials])
                out[name] = (float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0)
            else:
                out[name] = (d.neutral, 0.0)
        return out

    def pose(self) -> Pose:
        """The mean posture as a validated :class:`Pose` (limits checked)."""
        return Pose({k: m for k, (m, _) in self.mean_sd().items() if k in self.measured},
                    source=self.source)


def grasp_angles(subject_dir: str | Path, grasp: str, *, trial: int | None = None) -> GraspAngles:
    """Glove angles of a grasp's trials (or one trial), each averaged over its hold window."""
    from handfe.config import from_dict
    from handfe.emg import read_subject, trial_hold_window

    subject = read_subject(subject_dir)
    specs = subject.trials(grasp, trial)
    settings = from_dict(GloveSettings, subject.glove_table, source=str(subject.trials_file),
                         prefix="glove.")
    cal = None
    if settings.format == "raw":
        if not settings.calibration:
            raise InputError(f"{subject.trials_file}: glove.calibration is required for "
                             "format = 'raw'")
        cal = read_glove_calibration(subject.path(settings.calibration))
    emg_settings = None
    rows = []
    measured: tuple[str, ...] | None = None
    for spec in specs:
        if not spec.glove:
            raise InputError(f"{subject.trials_file}: grasp '{grasp}' trial {spec.trial} has no "
                             "'glove' file")
        path = subject.path(spec.glove)
        t, ang = glove_angles(path, settings, cal)
        # the trial's hold_s, or (no hold_s, or [emg] hold = "detect") the hold detected in
        # the trial's EMG, which shares the glove's clock
        emg_settings = emg_settings or subject.emg_settings()
        hold = trial_hold_window(subject, spec, emg_settings)
        sel = (t >= hold[0]) & (t <= hold[1])
        if sel.sum() < 1:
            raise InputError(f"{path}: hold window {hold[0]:g}-{hold[1]:g} s lies outside the "
                             f"recording ({t[0]:g}-{t[-1]:g} s)")
        names = tuple(ang)
        if measured is None:
            measured = names
        elif set(names) != set(measured):
            raise InputError(f"{path}: measures other DOFs than the grasp's first trial")
        rows.append((spec.trial, (float(hold[0]), float(hold[1])),
                     {k: float(v[sel].mean()) for k, v in ang.items()}))
    src = f"{subject.trials_file} grasp '{grasp}'"
    return GraspAngles(subject.id, grasp, src, measured or (), tuple(rows))


def grasp_pose(subject_dir: Path, grasp: str) -> Pose:
    """The grasp's posture: glove angles averaged over hold windows and trials, as a
    :class:`Pose` (limits checked; DOFs the glove does not measure are neutral)."""
    return grasp_angles(subject_dir, grasp).pose()

"""Joint degrees of freedom and hand postures.

The 27 DOF, their limits and sign conventions are data: ``anatomy/joints.csv``. A :class:`Pose`
holds a value per DOF (degrees for rotations, mm for translations); DOFs it does not name are at
their neutral value. Forward kinematics (bone frames from a pose) lives in :mod:`handfe.anatomy`,
which knows the bone lengths.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

from handfe.config import load_toml
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

"""Anatomy tables of ``anatomy/``: bones, digit rays, ligaments and tendon insertions.

All tables are CSV files with ``#`` comment headers that state their sources and conventions.
Values are read as plain records; scaling to a subject happens in :mod:`handfe.anatomy.skeleton`.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from handfe.errors import InputError
from handfe.paths import ANATOMY_DIR

PHALANX_SEGMENTS = ("proximal", "middle", "distal")
DIGIT_BONES = {
    "thumb": ("thumb_mc", "thumb_pp", "thumb_dp"),
    "index": ("index_mc", "index_pp", "index_mp", "index_dp"),
    "middle": ("middle_mc", "middle_pp", "middle_mp", "middle_dp"),
    "ring": ("ring_mc", "ring_pp", "ring_mp", "ring_dp"),
    "little": ("little_mc", "little_pp", "little_mp", "little_dp"),
}
CARPALS = ("scaphoid", "lunate", "triquetrum", "pisiform", "trapezium", "trapezoid", "capitate",
           "hamate")
MUSCLES = ("FDS", "FDP", "APL", "APB", "AP", "FPB", "FDI", "SDI", "TDI")


@dataclass(frozen=True)
class BoneRow:
    bone: str
    kind: str  # phalanx | metacarpal | carpal
    digit: str  # thumb..little | hand
    segment: str  # metacarpal | proximal | middle | distal | carpal
    parent_joint: str
    length_frac: float | None  # of hand length
    width_frac: float | None  # of hand breadth
    height_frac: float | None  # of hand breadth
    carpal_size_mm: tuple[float, float, float] | None  # (length y, width x, height z) at HB 87
    carpal_centre_frac: tuple[float, float, float] | None  # (x/HB, y/HL, z/HT)


@dataclass(frozen=True)
class RayRow:
    digit: str
    cmc_frac: tuple[float, float, float]  # (x/HB, y/HL, z/HT)
    spread_deg: float
    palmar_tilt_deg: float
    axial_pronation_deg: float
    abduction_sign: float


@dataclass(frozen=True)
class LigamentRow:
    name: str
    group: str
    bone_a: str
    point_a: tuple[float, float, float]
    bone_b: str
    point_b: tuple[float, float, float]
    k_N_per_mm: float
    eps_toe: float
    strain_ref: float
    source: str


@dataclass(frozen=True)
class InsertionRow:
    muscle: str
    digit: str
    bone: str
    point: tuple[float, float, float]
    toward_bone: str
    toward: tuple[float, float, float]
    share: float


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        raise InputError(f"{path}: anatomy table not found")
    with path.open() as fh:
        return list(csv.DictReader(line for line in fh if not line.lstrip().startswith("#")))


def _f(row: dict[str, str], key: str, path: Path) -> float:
    try:
        return float(row[key])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path}: column '{key}' = {row.get(key)!r} is not a number") from None


def _opt(row: dict[str, str], key: str, path: Path) -> float | None:
    return None if not row.get(key) else _f(row, key, path)


def _vec(row: dict[str, str], keys: tuple[str, str, str], path: Path) -> tuple[float, ...]:
    return tuple(_f(row, k, path) for k in keys)


@lru_cache(maxsize=2)
def bones(directory: str | None = None) -> dict[str, BoneRow]:
    """The 27 bones, keyed by name (file order)."""
    path = Path(directory or ANATOMY_DIR) / "bones.csv"
    out: dict[str, BoneRow] = {}
    for r in _rows(path):
        carpal = r["kind"] == "carpal"
        out[r["bone"]] = BoneRow(
            r["bone"], r["kind"], r["digit"], r["segment"], r["parent_joint"],
            _opt(r, "length_frac", path), _opt(r, "width_frac", path),
            _opt(r, "height_frac", path),
            _vec(r, ("carpal_len_mm", "carpal_w_mm", "carpal_h_mm"), path) if carpal else None,
            _vec(r, ("cx_frac", "cy_frac", "cz_frac"), path) if carpal else None)
    return out


@lru_cache(maxsize=2)
def rays(directory: str | None = None) -> dict[str, RayRow]:
    """Digit rays (CMC position and neutral orientation), keyed by digit."""
    path = Path(directory or ANATOMY_DIR) / "rays.csv"
    cmc = ("cmc_x_frac", "cmc_y_frac", "cmc_z_frac")
    return {r["digit"]: RayRow(r["digit"], _vec(r, cmc, path),
                               _f(r, "spread_deg", path), _f(r, "palmar_tilt_deg", path),
                               _f(r, "axial_pronation_deg", path), _f(r, "abduction_sign", path))
            for r in _rows(path)}


@lru_cache(maxsize=2)
def ligaments(directory: str | None = None) -> tuple[LigamentRow, ...]:
    """The ligament springs (see the header of ``anatomy/ligaments.csv`` for the force law)."""
    path = Path(directory or ANATOMY_DIR) / "ligaments.csv"
    return tuple(LigamentRow(r["ligament"], r["group"], r["bone_a"],
                             _vec(r, ("ua", "va", "wa"), path),
                             r["bone_b"], _vec(r, ("ub", "vb", "wb"), path),
                             _f(r, "k_N_per_mm", path), _f(r, "eps_toe", path),
                             _f(r, "strain_ref", path), r["source"])
                 for r in _rows(path))


@lru_cache(maxsize=2)
def insertions(directory: str | None = None) -> tuple[InsertionRow, ...]:
    """Tendon insertions of the nine muscles (FDS and FDP have one per digit 2-5)."""
    path = Path(directory or ANATOMY_DIR) / "insertions.csv"
    return tuple(InsertionRow(r["muscle"], r["digit"], r["bone"], _vec(r, ("u", "v", "w"), path),
                              r["toward_bone"], _vec(r, ("tu", "tv", "tw"), path),
                              _f(r, "share", path))
                 for r in _rows(path))


#: workflow ``tendon_split`` values: "equal" is anatomy/insertions.csv's ``share``; the others
#: are named splits of anatomy/tendon_splits.csv
TENDON_SPLITS = ("equal", "holzbaur2005")


def tendon_shares(split: str = "equal", directory: str | None = None
                  ) -> dict[tuple[str, str], float]:
    """(muscle, digit) -> the share of the muscle's force its tendon on that digit carries.

    ``"equal"``: insertions.csv's ``share`` column (FDS, FDP: 1/4 per finger). Another name: its
    rows of tendon_splits.csv (weights normalised per muscle) over those shares; a muscle it
    does not list keeps them. A split must give a listed muscle to every digit it inserts on.
    The table is read once per (split, directory); each call returns a dict of its own."""
    return dict(_tendon_shares(split, directory))


@lru_cache(maxsize=4)
def _tendon_shares(split: str, directory: str | None) -> tuple[tuple[tuple[str, str], float], ...]:
    shares = {(r.muscle, r.digit): r.share for r in insertions(directory)}
    if split == "equal":
        return tuple(shares.items())
    path = Path(directory or ANATOMY_DIR) / "tendon_splits.csv"
    rows = _rows(path)
    weights: dict[str, dict[str, float]] = {}
    for r in rows:
        if r["split"] == split:
            weights.setdefault(r["muscle"], {})[r["digit"]] = _f(r, "weight", path)
    if not weights:
        known = sorted({r["split"] for r in rows} | {"equal"})
        raise InputError(f"{path}: no tendon split {split!r} (known: {', '.join(known)})")
    for muscle, w in weights.items():
        digits = {d for (m, d) in shares if m == muscle}
        if set(w) != digits or min(w.values()) < 0.0 or sum(w.values()) <= 0.0:
            raise InputError(f"{path}: split {split!r} gives {muscle} the weights {w}; it needs "
                             "one weight >= 0 per digit it inserts on "
                             f"({', '.join(sorted(digits))}), not all 0")
        total = sum(w.values())
        shares.update({(muscle, d): v / total for d, v in w.items()})
    return tuple(shares.items())


def ligament_force_N(length_mm: float, slack_length_mm: float, k_N_per_mm: float,
                     eps_toe: float) -> float:
    """Tensile force (N, >= 0) of a ligament spring at ``length_mm`` (Blankevoort & Huiskes 1991):
    zero when slack, quadratic toe region up to strain ``eps_toe``, then linear with stiffness
    ``k_N_per_mm``. Continuous in value and slope."""
    L0 = slack_length_mm
    e = (length_mm - L0) / L0
    if e <= 0.0:
        return 0.0
    if e <= eps_toe:
        return k_N_per_mm * L0 * e * e / (2.0 * eps_toe)
    return k_N_per_mm * L0 * (e - 0.5 * eps_toe)

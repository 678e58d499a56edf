"""Subject anthropometry (``subjects/<id>/anthropometry.toml``) as a typed, frozen dataclass.

Lengths in mm. Digit dimensions not given in the file are scaled from the anatomy tables
(segment lengths from hand length, widths from hand breadth), so a new subject needs only the
[hand] table.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from handfe.config import bounds, load
from handfe.errors import ConfigError
from handfe.kinematics import DIGITS

# Default widths (mm) of the digits at their base (MCP level) and at the fingertip for a hand
# breadth of 87 mm (50th percentile adult male; Pheasant & Haslegrave 2006, Bodyspace 3rd ed.,
# finger breadths; index fingertip 16.7 mm: brief S3). Scaled by hand breadth / 87 mm.
_REF_BREADTH_MM = 87.0
_BASE_WIDTH_MM = {"thumb": 23.0, "index": 19.0, "middle": 19.5, "ring": 18.0, "little": 16.0}
_TIP_WIDTH_MM = {"thumb": 20.0, "index": 16.7, "middle": 17.2, "ring": 16.2, "little": 14.5}


@dataclass(frozen=True)
class Hand:
    """Whole-hand measures (mm). Hand length: distal wrist crease to the middle fingertip."""

    hand_length_mm: float = field(default=189.0, metadata=bounds(120.0, 260.0))
    hand_breadth_mm: float = field(default=87.0, metadata=bounds(55.0, 120.0))
    hand_thickness_mm: float = field(default=33.0, metadata=bounds(18.0, 50.0))
    wrist_breadth_mm: float = field(default=63.0, metadata=bounds(40.0, 90.0))
    wrist_thickness_mm: float = field(default=40.0, metadata=bounds(25.0, 60.0))
    thenar_width_mm: float = field(default=32.0, metadata=bounds(18.0, 50.0))
    forearm_stub_mm: float = field(default=22.0, metadata=bounds(10.0, 60.0))
    skin_thickness_mm: float = field(default=1.2, metadata=bounds(0.5, 3.0))


@dataclass(frozen=True)
class Fingertip:
    """Index fingertip pad (brief S3; reference/fingertip_anthropometry.csv, mean row)."""

    width_mm: float = field(default=16.7, metadata=bounds(10.0, 25.0))
    height_mm: float = field(default=12.0, metadata=bounds(7.0, 20.0))
    pad_length_mm: float = field(default=12.0, metadata=bounds(6.0, 20.0))
    bone_width_mm: float = field(default=7.4, metadata=bounds(3.0, 12.0))
    bone_height_mm: float = field(default=4.0, metadata=bounds(2.0, 8.0))
    pulp_thickness_mm: float = field(default=6.4, metadata=bounds(3.0, 10.0))


@dataclass(frozen=True)
class Digit:
    """One digit. ``segment_lengths_mm``: joint-centre to joint-centre lengths, proximal to distal:
    [metacarpal, proximal, middle, distal] (thumb: [metacarpal, proximal, distal]); the distal
    length runs from the DIP (thumb IP) centre to the fingertip. Widths are outer (skin) widths."""

    segment_lengths_mm: tuple[float, ...] = field(default=(), metadata=bounds(5.0, 120.0))
    base_width_mm: float = field(default=0.0, metadata=bounds(0.0, 35.0))
    tip_width_mm: float = field(default=0.0, metadata=bounds(0.0, 30.0))
    height_ratio: float = field(default=0.8, metadata=bounds(0.5, 1.0))


@dataclass(frozen=True)
class Digits:
    thumb: Digit | None = None
    index: Digit | None = None
    middle: Digit | None = None
    ring: Digit | None = None
    little: Digit | None = None


@dataclass(frozen=True)
class Anthropometry:
    """A subject's hand (right hand; mm). Load with :func:`load_subject`."""

    subject: str = "S01"
    description: str = ""
    hand: Hand = field(default_factory=Hand)
    fingertip: Fingertip = field(default_factory=Fingertip)
    digits: Digits = field(default_factory=Digits)
    source: str = "<defaults>"

    def digit(self, name: str) -> Digit:
        """Dimensions of digit ``name`` (filled from the tables if the file left them out)."""
        d = getattr(self.digits, name)
        if d is None:
            raise KeyError(name)
        return d


def _default_digit(name: str, hand: Hand) -> Digit:
    from handfe.anatomy.tables import DIGIT_BONES, bones

    table = bones()
    lengths = tuple(round(table[b].length_frac * hand.hand_length_mm, 2)
                    for b in DIGIT_BONES[name])
    s = hand.hand_breadth_mm / _REF_BREADTH_MM
    return Digit(lengths, round(_BASE_WIDTH_MM[name] * s, 2), round(_TIP_WIDTH_MM[name] * s, 2))


def complete(a: Anthropometry) -> Anthropometry:
    """Fill missing digits / zero widths from the tables and check consistency."""
    filled = {}
    for name in DIGITS:
        d = getattr(a.digits, name)
        dflt = _default_digit(name, a.hand)
        if d is None:
            d = dflt
        else:
            d = replace(d, segment_lengths_mm=d.segment_lengths_mm or dflt.segment_lengths_mm,
                        base_width_mm=d.base_width_mm or dflt.base_width_mm,
                        tip_width_mm=d.tip_width_mm or dflt.tip_width_mm)
        n_expected = 3 if name == "thumb" else 4
        if len(d.segment_lengths_mm) != n_expected:
            raise ConfigError(f"{a.source}: 'digits.{name}.segment_lengths_mm' = "
                              f"{list(d.segment_lengths_mm)}: expected {n_expected} values "
                              "(metacarpal, proximal, " + ("" if name == "thumb" else "middle, ")
                              + "distal)")
        if d.tip_width_mm > d.base_width_mm:
            raise ConfigError(f"{a.source}: 'digits.{name}.tip_width_mm' = {d.tip_width_mm:g} "
                              f"is larger than base_width_mm = {d.base_width_mm:g}")
        t = a.hand.skin_thickness_mm
        if t > 0.12 * d.tip_width_mm:
            raise ConfigError(f"{a.source}: 'hand.skin_thickness_mm' = {t:g} is too thick for "
                              f"the {name} tip (width {d.tip_width_mm:g} mm)")
        filled[name] = d
    ft = a.fingertip
    tissue = ft.height_mm - ft.bone_height_mm - ft.pulp_thickness_mm
    if tissue < a.hand.skin_thickness_mm + 0.3:
        raise ConfigError(f"{a.source}: 'fingertip.pulp_thickness_mm' = {ft.pulp_thickness_mm:g}:"
                          f" height {ft.height_mm:g} - bone {ft.bone_height_mm:g} - pulp leaves "
                          f"{tissue:.2f} mm dorsal tissue, less than the skin + 0.3 mm")
    if ft.bone_width_mm > ft.width_mm - 2 * a.hand.skin_thickness_mm - 1.0:
        raise ConfigError(f"{a.source}: 'fingertip.bone_width_mm' = {ft.bone_width_mm:g} leaves "
                          f"no tissue beside the bone (fingertip width {ft.width_mm:g} mm)")
    return replace(a, digits=Digits(**filled))


def load_subject(subject_dir: str | Path) -> Anthropometry:
    """Read ``<subject_dir>/anthropometry.toml`` (or the file itself) into :class:`Anthropometry`.

    Unknown keys, wrong types and out-of-range values raise :class:`ConfigError` naming the
    file, the key and the value."""
    p = Path(subject_dir)
    path = p if p.suffix == ".toml" else p / "anthropometry.toml"
    a = load(Anthropometry, path)
    if a.source == "<defaults>":
        a = replace(a, source=str(path))
    return complete(a)


def default_subject() -> Anthropometry:
    """The 50th-percentile adult male of the tables (subjects/S01 differs only in the pulp
    thickness under the distal phalanx: 5.8 mm instead of the brief's 6.4 mm)."""
    return complete(Anthropometry())

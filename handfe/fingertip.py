"""Index fingertip geometry and tetrahedral mesh (units: mm).

Coordinate convention
---------------------
Finger axis along +x (proximal cut face at x = 0, distal tip at larger x), dorsal (nail) side
+z, palmar pad facing -z, y across the finger. A plate at angle theta to the finger axis
approaches the pad from -z (see :func:`handfe.contact.plate`).

Geometry (from ``reference/fingertip_anthropometry.csv``, one row per subject, ``mean`` by
default)
--------
* Outer shape, a "bi-ellipsoid": the frontal cross-section is two half ellipses with the
  half width ``W = w0/2`` (``frontal_ellipse_a`` equals ``w0`` in every row: it is the full
  width), a palmar semi-axis ``b = frontal_ellipse_b`` (= ``long_ellipse_b``) below the
  ellipse centre z = 0 and a dorsal semi-axis ``hd = h0 - b`` above it, so the height is h0.
  From the proximal cut (x = 0) to ``x = Lp`` (``proximal_length_mm``, default 10) the section
  is constant; beyond, it closes as the sagittal ellipse of semi-axis ``a = long_ellipse_a``
  (the tip is at x = Lp + a). The palmar pad is the lower half (z <= 0) of this surface.
* Distal phalanx, a cavity (surface tagged ``bone``, to be clamped as rigid): an elliptic
  cylinder of width ``wp`` and height ``hp``, parallel to the finger axis, running out through
  the proximal face, closed distally by a half ellipsoid of length ``bone_cap_length``. Its
  palmar surface is ``DN0`` above the pad where the pad is flat (x <= Lp): the pulp thickness
  under the bone is DN0 (6.4 mm for the mean). The bone tip (its distal end, on its axis) is
  placed so that the pulp thickness from it along the finger axis (90 deg) is DN90; the cap
  is the shortest half ellipsoid that keeps the bone at least ``nail_thickness + 0.3 mm``
  below the dorsal surface. Measured from the bone tip in the sagittal plane (0 deg =
  palmar, 90 deg = distal) the model's pulp thicknesses are ``DN0_model_mm``,
  ``DN45_model_mm``, ``DN90_model_mm`` (mean subject: 6.02 / 3.84 / 2.30 mm vs 6.4 / 3.3 /
  2.3 measured: the two-ellipse outline is more pointed than a real tip). ``beta_deg`` is
  carried along but not used (the bone is kept parallel to the finger axis).
* Nail: a separate volume, the outer ``nail_thickness_mm`` (default 0.5) of the dorsal shell
  above the bone top (z >= bone top + 0.2 mm) from ``x = Lp - 3 mm`` to its distal end;
  linear elastic (E = 170 MPa) in the solver. Where the dorsal side is too thin for the nail
  plus 0.3 mm of tissue over the bone (subject S3: 0.6 mm), the nail is thinned to fit
  (S3: 0.3 mm; ``FingertipGeometry.nail_thickness_mm`` holds the value used).
* Half model (``half=True``): the geometry is symmetric about the sagittal plane y = 0, and so
  is the plate load (its normal lies in that plane), so only y >= 0 is meshed and the face
  y = 0 is tagged ``symmetry`` (the scene holds u_y = 0 there and doubles forces and areas).
* Soft tissue: homogeneous ("pulp") or layered: a skin layer of ``skin_thickness_mm`` (the
  bi-ellipsoid with all semi-axes reduced by the thickness: exact on the principal axes) over
  "subcutaneous" tissue.

Tags (``FingertipMesh.tags``: name -> id): cells ``pulp`` (1) or ``skin`` (2) +
``subcutaneous`` (3), ``nail`` (4); facets ``pad`` (11: outer palmar skin, z <= 0, where the
plate touches), ``dorsal`` (12: outer dorsal skin), ``nail_outer`` (13), ``bone`` (14: the
cavity surface), ``proximal`` (15: the cut face at x = 0) and, for a half model, ``symmetry``
(16: the face y = 0). The mesh is linear (P2 fields are
made in dolfinx on it), refined on the pad; gmsh runs on rank 0 only.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from handfe.errors import InputError
from handfe.paths import REFERENCE_DIR

ANTHROPOMETRY_CSV = REFERENCE_DIR / "fingertip_anthropometry.csv"

CELL_TAGS = {"pulp": 1, "skin": 2, "subcutaneous": 3, "nail": 4}
FACET_TAGS = {"pad": 11, "dorsal": 12, "nail_outer": 13, "bone": 14, "proximal": 15}
SYMMETRY_TAG = 16  # the cut face y = 0 of a half model (``half=True``)


def facet_tag_map(half: bool) -> dict[str, int]:
    """Boundary names -> facet tags of a fingertip mesh (with ``symmetry`` for a half model)."""
    return {**FACET_TAGS, "symmetry": SYMMETRY_TAG} if half else dict(FACET_TAGS)

# global element size / size on the pad (mm) per level. The deflection converges with the
# global size, the contact area with the pad size (docs/contact.md, "seventh session"):
# "default" is within 2 % of "fine" (the benchmark's reference) in both at 4 N. "coarse" is
# for fast end-to-end tests of other modules; it is NOT validated.
MESH_LEVELS = {"coarse": (3.5, 2.0), "reduced": (2.5, 1.5), "default": (2.5, 1.0),
               "fine": (1.0, 0.45)}
PAD_SIZE_RATIO = 0.6  # pad size = ratio * global size when h_mm is given
MIN_TISSUE_OVER_BONE_MM = 0.3
MIN_NAIL_MM = 0.25

_COLUMNS = ("w0_mm", "h0_mm", "hp_mm", "wp_mm", "DN0_mm", "DN45_mm", "DN90_mm",
            "long_ellipse_a_mm", "long_ellipse_b_mm", "frontal_ellipse_a_mm",
            "frontal_ellipse_b_mm", "beta_deg")


@dataclass(frozen=True)
class FingertipGeometry:
    """Fingertip dimensions (mm); see the module docstring for their meaning."""

    subject: str
    w0_mm: float
    h0_mm: float
    hp_mm: float
    wp_mm: float
    DN0_mm: float
    DN45_mm: float
    DN90_mm: float
    long_ellipse_a_mm: float
    long_ellipse_b_mm: float
    frontal_ellipse_a_mm: float
    frontal_ellipse_b_mm: float
    beta_deg: float
    proximal_length_mm: float = 10.0
    nail_thickness_mm: float = 0.5
    # derived (filled by fingertip_geometry)
    bone_z_mm: float = 0.0
    bone_cap_x_mm: float = 0.0
    bone_cap_length_mm: float = 0.0
    DN0_model_mm: float = 0.0
    DN45_model_mm: float = 0.0
    DN90_model_mm: float = 0.0

    @property
    def half_width_mm(self) -> float:
        return 0.5 * self.w0_mm

    @property
    def palmar_depth_mm(self) -> float:
        return self.frontal_ellipse_b_mm

    @property
    def dorsal_height_mm(self) -> float:
        return self.h0_mm - self.frontal_ellipse_b_mm

    @property
    def tip_length_mm(self) -> float:
        return self.long_ellipse_a_mm

    @property
    def length_mm(self) -> float:
        """x of the distal tip (the proximal face is at x = 0)."""
        return self.proximal_length_mm + self.long_ellipse_a_mm

    @property
    def bone_top_mm(self) -> float:
        return self.bone_z_mm + 0.5 * self.hp_mm

    @property
    def bone_bottom_mm(self) -> float:
        return self.bone_z_mm - 0.5 * self.hp_mm

    @property
    def bone_tip_x_mm(self) -> float:
        return self.bone_cap_x_mm + self.bone_cap_length_mm

    @property
    def nail_z_min_mm(self) -> float:
        """The nail covers the dorsal shell above this height (0.2 mm above the bone top: a
        plane tangent to the bone would break the OCC booleans)."""
        return self.bone_top_mm + 0.2

    @property
    def nail_start_x_mm(self) -> float:
        return max(0.5, self.proximal_length_mm - 3.0)

    def outer_volume_mm3(self, shrink_mm: float = 0.0) -> float:
        """Volume of the bi-ellipsoid body (semi-axes reduced by shrink_mm), x >= 0."""
        t = shrink_mm
        W, b, hd, a = (self.half_width_mm - t, self.palmar_depth_mm - t,
                       self.dorsal_height_mm - t, self.tip_length_mm - t)
        return math.pi * W * (b + hd) / 2 * self.proximal_length_mm + math.pi * a * W * (b + hd) / 3

    def bone_volume_mm3(self) -> float:
        """Volume of the bone cavity inside the body (x >= 0)."""
        ab = math.pi * 0.25 * self.wp_mm * self.hp_mm
        return ab * self.bone_cap_x_mm + 2.0 / 3.0 * ab * self.bone_cap_length_mm

    def outer_z(self, x: np.ndarray, upper: bool) -> np.ndarray:
        """z of the outer surface in the sagittal plane y = 0 (palmar if not upper)."""
        bz = self.dorsal_height_mm if upper else self.palmar_depth_mm
        u = np.clip((np.asarray(x, float) - self.proximal_length_mm) / self.tip_length_mm, 0, 1)
        return (1 if upper else -1) * bz * np.sqrt(np.maximum(1 - u * u, 0.0))

    def pulp_thickness_mm(self, angle_deg: float) -> float:
        """Model pulp thickness (mm) from the bone tip along the direction at angle_deg in the
        sagittal plane (0 = palmar, -z; 90 = distal, +x)."""
        s, c = math.sin(math.radians(angle_deg)), math.cos(math.radians(angle_deg))
        lo, hi = 0.0, 100.0
        for _ in range(80):
            m = 0.5 * (lo + hi)
            inside = _inside(self, self.bone_tip_x_mm + m * s, self.bone_z_mm - m * c) <= 0
            lo, hi = (m, hi) if inside else (lo, m)
        return lo


def _inside(g: FingertipGeometry, x: float, z: float) -> float:
    bz = g.palmar_depth_mm if z < 0 else g.dorsal_height_mm
    u = max(x - g.proximal_length_mm, 0.0) / g.tip_length_mm
    return u * u + (z / bz) ** 2 - 1.0


def _bone_clearance(g: FingertipGeometry, xc: float, rx: float) -> float:
    """Smallest (dorsal surface - bone top) over the bone's length."""
    hb = 0.5 * g.hp_mm
    xs = np.linspace(0.0, xc + rx, 400)
    top = g.bone_z_mm + hb * np.sqrt(np.clip(1 - ((np.maximum(xs - xc, 0)) / rx) ** 2, 0, 1))
    return float(np.min(g.outer_z(xs, upper=True) - top))


def read_anthropometry(path: Path | str = ANTHROPOMETRY_CSV) -> dict[str, dict[str, float]]:
    """Rows of the anthropometry table: subject -> {column: value}."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from e
    out: dict[str, dict[str, float]] = {}
    for i, r in enumerate(rows, start=2):
        name = (r.get("subject") or "").strip()
        vals = {}
        for c in _COLUMNS:
            try:
                vals[c] = float(r[c])
            except (KeyError, TypeError, ValueError) as e:
                raise InputError(f"{path}: line {i} (subject {name!r}) column {c!r}: "
                                 f"missing or not a number ({r.get(c)!r})") from e
        out[name] = vals
    return out


def fingertip_geometry(subject: str = "mean", *, proximal_length_mm: float = 10.0,
                       nail_thickness_mm: float = 0.5,
                       csv_path: Path | str = ANTHROPOMETRY_CSV) -> FingertipGeometry:
    """Geometry of the index fingertip of ``subject`` (S1..S5 or "mean"), mm.

    Raises InputError naming the subject (and the ones available) if it is not in the
    table, or if its dimensions do not leave room for the bone under the nail."""
    rows = read_anthropometry(csv_path)
    valid = [s for s in rows if s != "std"]
    if subject not in valid:
        raise InputError(f"unknown fingertip subject {subject!r} in {Path(csv_path).name} "
                         f"(column 'subject'); available: {', '.join(valid)}")
    r = rows[subject]
    for c in _COLUMNS[:-1]:
        if r[c] <= 0:
            raise InputError(f"{csv_path}: subject {subject!r} column {c!r} must be > 0, "
                             f"got {r[c]}")
    if not (proximal_length_mm > 0 and 0 < nail_thickness_mm < 2.0):
        raise InputError(f"proximal_length_mm must be > 0 and nail_thickness_mm in (0, 2), got "
                         f"{proximal_length_mm}, {nail_thickness_mm}")
    g = FingertipGeometry(subject=subject, **r, proximal_length_mm=float(proximal_length_mm),
                          nail_thickness_mm=float(nail_thickness_mm))
    z_bc = -g.palmar_depth_mm + g.DN0_mm + 0.5 * g.hp_mm
    g = replace(g, bone_z_mm=z_bc)
    room = g.dorsal_height_mm - g.bone_top_mm - MIN_TISSUE_OVER_BONE_MM
    if room < g.nail_thickness_mm:
        # thin dorsal side (subject S3): the nail is thinned to fit, down to MIN_NAIL_MM
        if room < MIN_NAIL_MM:
            raise InputError(f"fingertip subject {subject!r}: the bone (DN0 {g.DN0_mm} + hp "
                             f"{g.hp_mm} mm above the pad) leaves no room for the nail under "
                             f"the height h0 {g.h0_mm} mm")
        g = replace(g, nail_thickness_mm=round(room, 3))
    # bone tip: thickness DN90 along the bone axis
    lo, hi = 0.0, 100.0
    for _ in range(80):
        m = 0.5 * (lo + hi)
        lo, hi = (m, hi) if _inside(g, m, z_bc) <= 0 else (lo, m)
    x_tip = lo - g.DN90_mm
    # the bluntest-possible tuft: the shortest cap that keeps the bone under the nail
    need = g.nail_thickness_mm + MIN_TISSUE_OVER_BONE_MM
    for rx in np.arange(0.5 * g.hp_mm, x_tip - 0.5, 0.05):
        if _bone_clearance(g, x_tip - rx, rx) >= need - 1e-3:
            break
    else:
        raise InputError(f"fingertip subject {subject!r}: no bone cap fits DN90 "
                         f"{g.DN90_mm} mm under the nail")
    g = replace(g, bone_cap_x_mm=float(x_tip - rx), bone_cap_length_mm=float(rx))
    return replace(g, DN0_model_mm=g.pulp_thickness_mm(0.0),
                   DN45_model_mm=g.pulp_thickness_mm(45.0),
                   DN90_model_mm=g.pulp_thickness_mm(90.0))


@dataclass
class FingertipMesh:
    """A meshed fingertip. ``tags`` maps names to cell/facet tag ids (module docstring);
    ``finger_axis`` (+x) and ``pad_normal`` (outward normal of the pad, -z) are unit numpy
    vectors; cell counts are global; meshing_time_s is gmsh's wall time on rank 0."""

    mesh: Any
    cell_tags: Any
    facet_tags: Any
    tags: dict[str, int]
    geometry: FingertipGeometry
    finger_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    pad_normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    num_cells: int = 0
    num_vertices: int = 0
    cells_per_tag: dict[str, int] = field(default_factory=dict)
    meshing_time_s: float = 0.0
    h_mm: float = 0.0
    h_pad_mm: float = 0.0
    layered: bool = False
    skin_thickness_mm: float = 0.0
    half: bool = False
    from_cache: bool = False


def mesh_cache_path(geom: FingertipGeometry, h: float, h_pad: float, layered: bool,
                    skin_t: float, half: bool) -> Path | None:
    """Where the gmsh mesh of these inputs is cached (:mod:`handfe.meshcache`), None if
    ``HANDFE_MESH_CACHE=0``. The key hashes the inputs, the gmsh version and this module's
    source, so a change to the mesher misses."""
    from handfe.meshcache import cache_path

    return cache_path("fingertip", [asdict(geom), h, h_pad, layered,
                                    skin_t if layered else 0.0, half], [Path(__file__)])


def mesh_sizes(level: str = "default", h_mm: float | None = None,
               h_pad_mm: float | None = None) -> tuple[float, float]:
    """(global size, pad size) in mm for a level, or for an explicit h_mm (pad size h_pad_mm,
    default PAD_SIZE_RATIO h_mm). h_pad_mm alone refines the level's pad."""
    if h_mm is not None:
        h = float(h_mm)
        if not (0.2 <= h <= 5.0):
            raise InputError(f"mesh size h_mm must be within 0.2..5 mm, got {h_mm!r}")
        pad = PAD_SIZE_RATIO * h
    elif level not in MESH_LEVELS:
        raise InputError(f"unknown mesh level {level!r}; use one of {', '.join(MESH_LEVELS)} "
                         "or a numeric size")
    else:
        h, pad = MESH_LEVELS[level]
    if h_pad_mm is not None:
        pad = float(h_pad_mm)
        if not (0.2 <= pad <= h):
            raise InputError(f"pad element size h_pad_mm must be within 0.2 mm..the global "
                             f"size {h:g} mm, got {h_pad_mm!r}")
    return h, pad


def _ellipsoid_part(occ, centre, semi, box, pole_x: bool = False) -> list:
    """Ellipsoid (centre, semi-axes) intersected with an axis-aligned box (x0, y0, z0, x1,
    y1, z1). Cutting first avoids fusing surfaces that touch tangentially, which makes
    OpenCASCADE run out of memory. pole_x puts the sphere's poles on the x axis (keeps them
    off a cut plane x = const, where gmsh cannot mesh the degenerate loop)."""
    e = occ.addSphere(*centre, 1.0)
    if pole_x:
        occ.rotate([(3, e)], *centre, 0, 1, 0, math.pi / 2)
    occ.dilate([(3, e)], *centre, *semi)
    x0, y0, z0, x1, y1, z1 = box
    b = occ.addBox(x0, y0, z0, x1 - x0, y1 - y0, z1 - z0)
    out, _ = occ.intersect([(3, e)], [(3, b)])
    return out


def _elliptic_cylinder(occ, x0, x1, zc, wy, hz, box=None) -> list:
    """Cylinder along x from x0 to x1, elliptic section (semi-axes wy, hz) centred at
    (y, z) = (0, zc), optionally intersected with an axis-aligned box."""
    c = occ.addCylinder(x0, 0, 0, x1 - x0, 0, 0, 1.0)
    occ.dilate([(3, c)], 0, 0, 0, 1.0, wy, hz)
    if zc:
        occ.translate([(3, c)], 0, 0, zc)
    if box is None:
        return [(3, c)]
    bx0, by0, bz0, bx1, by1, bz1 = box
    b = occ.addBox(bx0, by0, bz0, bx1 - bx0, by1 - by0, bz1 - bz0)
    out, _ = occ.intersect([(3, c)], [(3, b)])
    return out


def _bi_ellipsoid(occ, g: FingertipGeometry, t: float) -> int:
    """OCC volume of the outer body with all semi-axes reduced by t, for x >= 0."""
    W, a, Lp = g.half_width_mm - t, g.tip_length_mm - t, g.proximal_length_mm
    halves = []
    for bz, up in ((g.palmar_depth_mm - t, False), (g.dorsal_height_mm - t, True)):
        zlo, zhi = (0.0, bz + 1) if up else (-bz - 1, 0.0)
        e = _ellipsoid_part(occ, (Lp, 0, 0), (a, W, bz), (Lp, -W - 1, zlo, Lp + a + 1, W + 1, zhi))
        c = _elliptic_cylinder(occ, 0.0, Lp, 0.0, W, bz, (-1, -W - 1, zlo, Lp + 1, W + 1, zhi))
        f, _ = occ.fuse(e, c)
        halves += f
    body, _ = occ.fuse(halves[:1], halves[1:])
    if len(body) != 1:
        raise RuntimeError(f"fingertip body is not one volume ({len(body)})")
    return body[0][1]


def _bone(occ, g: FingertipGeometry) -> list:
    """The bone as two OCC volumes (elliptic cylinder from x = -1 to the cap centre, half
    ellipsoid cap): fusing them first makes later fragments fail in OCC 7.x."""
    hb, wb = 0.5 * g.hp_mm, 0.5 * g.wp_mm
    xc, zc = g.bone_cap_x_mm, g.bone_z_mm
    c = _elliptic_cylinder(occ, -1.0, xc, zc, wb, hb)
    e = _ellipsoid_part(occ, (xc, 0, zc), (g.bone_cap_length_mm, wb, hb),
                        (xc, -wb - 1, zc - hb - 1, xc + g.bone_cap_length_mm + 1, wb + 1,
                         zc + hb + 1), pole_x=True)
    return c + e


def _build_model(g: FingertipGeometry, h: float, h_pad: float, layered: bool,
                 skin_t: float, half: bool = False) -> dict[str, list[int]]:
    import gmsh

    occ = gmsh.model.occ
    # One fragment of the body with tools whose surfaces never coincide with its own (OCC
    # fails on coincident curved faces): the nail tool is a box above the bone top with the
    # body shrunk by the nail thickness carved out, the skin tool the body shrunk by the skin
    # thickness, and the bone. Pieces are then sorted by the inputs that contain them.
    body = _bi_ellipsoid(occ, g, 0.0)
    bone = _bone(occ, g)
    L = g.length_mm
    nbox = occ.addBox(g.nail_start_x_mm, -g.half_width_mm - 1, g.nail_z_min_mm,
                      L + 1 - g.nail_start_x_mm, g.w0_mm + 2, g.dorsal_height_mm + 1)
    inner_n = _bi_ellipsoid(occ, g, g.nail_thickness_mm)
    ntool, _ = occ.cut([(3, nbox)], [(3, inner_n)])
    tools = bone + ntool
    if layered:
        tools.append((3, _bi_ellipsoid(occ, g, skin_t)))
    if half:  # everything at y < 0 goes (its pieces are dropped below)
        W = g.half_width_mm
        tools.append((3, occ.addBox(-2, -W - 2, -g.palmar_depth_mm - 2, L + 4, W + 2,
                                    g.palmar_depth_mm + g.dorsal_height_mm + 4)))
    out, omap = occ.fragment([(3, body)], tools)
    children = [{t for (d, t) in m if d == 3} for m in omap]
    nb = len(bone)
    in_body = children[0]
    in_bone = set().union(*children[1:1 + nb])
    in_nail = set().union(*children[1 + nb:1 + nb + len(ntool)])
    in_inner = children[1 + nb + len(ntool)] if layered else set()
    in_cut = children[-1] if half else set()
    all_v = {t for (d, t) in out if d == 3}
    drop = sorted((all_v - in_body) | in_bone | in_cut)
    occ.remove([(3, t) for t in drop], recursive=True)
    occ.synchronize()
    keep = all_v - set(drop)
    nail_v = keep & in_nail
    sub_v = (keep & in_inner) - nail_v
    soft_v = keep - nail_v - sub_v
    groups: dict[str, list[int]] = {"nail": sorted(nail_v)}
    if layered:
        groups["skin"] = sorted(soft_v)
        groups["subcutaneous"] = sorted(sub_v)
    else:
        groups["pulp"] = sorted(soft_v)
    for name, vols in groups.items():
        if not vols:
            raise RuntimeError(f"no volume classified as {name!r}")
    # boundary surfaces: a point of the underlying surface says which geometric surface a
    # piece lies on (OCC bounding boxes of curved faces are far too loose to use)
    wb, hb = 0.5 * g.wp_mm, 0.5 * g.hp_mm
    ftags = facet_tag_map(half)
    fgroups: dict[str, list[int]] = {k: [] for k in ftags}
    for _, s in gmsh.model.getEntities(2):
        up, _ = gmsh.model.getAdjacencies(2, s)
        if len(up) != 1:
            continue
        lo, hi = gmsh.model.getParametrizationBounds(2, s)
        px, py, pz = gmsh.model.getValue(2, s, [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])])
        com = occ.getCenterOfMass(2, s)
        xb = max(px - g.bone_cap_x_mm, 0.0) / g.bone_cap_length_mm
        on_bone = abs(xb**2 + (py / wb) ** 2 + ((pz - g.bone_z_mm) / hb) ** 2 - 1) < 1e-5
        if half and abs(py) < 1e-7 and abs(com[1]) < 1e-7:
            fgroups["symmetry"].append(s)
        elif abs(px) < 1e-7 and abs(com[0]) < 1e-7:
            fgroups["proximal"].append(s)
        elif on_bone:
            fgroups["bone"].append(s)
        elif up[0] in nail_v:
            fgroups["nail_outer"].append(s)
        elif com[2] < 0:
            fgroups["pad"].append(s)
        else:
            fgroups["dorsal"].append(s)
    for name, vols in groups.items():
        gmsh.model.addPhysicalGroup(3, vols, CELL_TAGS[name])
        gmsh.model.setPhysicalName(3, CELL_TAGS[name], name)
    for name, surfs in fgroups.items():
        if not surfs:
            raise RuntimeError(f"fingertip mesh: no surface classified as {name!r}")
        gmsh.model.addPhysicalGroup(2, surfs, ftags[name])
        gmsh.model.setPhysicalName(2, ftags[name], name)
    # sizes: h everywhere, h_pad on the pad (growing to h over 3 mm), the nail thickness
    # resolved by elements no larger than 2x the nail thickness near the nail
    fld = gmsh.model.mesh.field
    d_pad = fld.add("Distance")
    fld.setNumbers(d_pad, "SurfacesList", fgroups["pad"])
    fld.setNumber(d_pad, "NumPointsPerCurve", 40)
    t_pad = fld.add("Threshold")
    fld.setNumber(t_pad, "InField", d_pad)
    fld.setNumber(t_pad, "SizeMin", h_pad)
    fld.setNumber(t_pad, "SizeMax", h)
    fld.setNumber(t_pad, "DistMin", 0.5)
    fld.setNumber(t_pad, "DistMax", 3.0)
    fields = [t_pad]
    h_nail = min(h, max(2.0 * g.nail_thickness_mm, 0.6 * h))
    if h_nail < h:
        d_n = fld.add("Distance")
        fld.setNumbers(d_n, "SurfacesList", fgroups["nail_outer"])
        fld.setNumber(d_n, "NumPointsPerCurve", 40)
        t_n = fld.add("Threshold")
        fld.setNumber(t_n, "InField", d_n)
        fld.setNumber(t_n, "SizeMin", h_nail)
        fld.setNumber(t_n, "SizeMax", h)
        fld.setNumber(t_n, "DistMin", 1.0)
        fld.setNumber(t_n, "DistMax", 3.0)
        fields.append(t_n)
    mn = fld.add("Min")
    fld.setNumbers(mn, "FieldsList", fields)
    fld.setAsBackgroundMesh(mn)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    gmsh.option.setNumber("Mesh.Algorithm", 6)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay: deterministic (HXT is not)
    gmsh.option.setNumber("General.NumThreads", 1)  # deterministic mesh
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.option.setNumber("Mesh.OptimizeThreshold", 0.5)
    gmsh.model.mesh.generate(3)
    gmsh.model.mesh.optimize("", force=False, niter=3)
    return {**groups, **fgroups}


def build_fingertip_mesh(geom: FingertipGeometry, *, level: str = "default",
                         h_mm: float | None = None, h_pad_mm: float | None = None,
                         layered: bool = False, skin_thickness_mm: float = 1.0,
                         half: bool = False, comm=None) -> FingertipMesh:
    """Mesh the fingertip with gmsh (rank 0) and distribute it over ``comm``.

    level: coarse | reduced | default | fine (global/pad sizes in MESH_LEVELS, mm); h_mm
    overrides the level (pad size 0.6 h_mm, or h_pad_mm). layered: skin (skin_thickness_mm) over
    subcutaneous tissue instead of one "pulp" volume. half: only y >= 0, the face y = 0 tagged
    ``symmetry`` (module docstring)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD if comm is None else comm
    h, h_pad = mesh_sizes(level, h_mm, h_pad_mm)
    if layered and not (0.2 <= skin_thickness_mm <= 3.0):
        raise InputError(f"skin_thickness_mm must be within 0.2..3 mm, got {skin_thickness_mm!r}")
    err = None
    cached = False
    t0 = time.perf_counter()
    if comm.rank == 0:
        import gmsh

        from handfe.gmshutil import ensure_gmsh, release_gmsh
        from handfe.meshcache import open_cached, write_mesh

        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)
        # the OCC booleans take ~5-8 s whatever the size (the meshing itself < 1 s at
        # default): a mesh made once is read back from the cache
        path = mesh_cache_path(geom, h, h_pad, layered, skin_thickness_mm, half)
        cached = open_cached(gmsh, path)
        try:
            if not cached:
                gmsh.model.add(f"fingertip_{geom.subject}")
                _build_model(geom, h, h_pad, layered, skin_thickness_mm, half)
                write_mesh(gmsh, path)
        except Exception as e:  # reported on every rank below
            err = f"{type(e).__name__}: {e}"
    err = comm.bcast(err, root=0)
    cached = comm.bcast(cached, root=0)
    if err is not None:
        if comm.rank == 0:
            release_gmsh(gmsh)
        raise RuntimeError(f"fingertip meshing failed for subject {geom.subject!r}: {err}")
    t_mesh = comm.bcast(time.perf_counter() - t0, root=0)
    import gmsh  # noqa: F811  (module needed as an argument on every rank)
    from dolfinx.io import gmshio

    msh, ct, ft = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    if comm.rank == 0:
        release_gmsh(gmsh)
    tags = {k: v for k, v in CELL_TAGS.items()
            if (k in ("skin", "subcutaneous")) == layered or k == "nail"}
    tags.update(facet_tag_map(half))
    n_local = msh.topology.index_map(3).size_local
    counts = {}
    for k in tags:
        if k in CELL_TAGS:
            idx = ct.find(CELL_TAGS[k])
            counts[k] = comm.allreduce(int(np.sum(idx < n_local)), op=MPI.SUM)
    nv = msh.topology.index_map(0).size_global
    return FingertipMesh(mesh=msh, cell_tags=ct, facet_tags=ft, tags=tags, geometry=geom,
                         num_cells=msh.topology.index_map(3).size_global, num_vertices=nv,
                         cells_per_tag=counts, meshing_time_s=float(t_mesh), h_mm=h,
                         h_pad_mm=h_pad, layered=layered,
                         skin_thickness_mm=float(skin_thickness_mm) if layered else 0.0,
                         half=half, from_cache=cached)

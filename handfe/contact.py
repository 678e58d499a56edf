"""Rigid obstacles, the contact law and contact outputs (units: mm, N, MPa; pressures
reported in kPa).

Obstacles
---------
Every obstacle is a small frozen dataclass (lengths in mm) with

* ``gap_normal(points, translation=None) -> (gap (n,), normal (n, 3))`` in NumPy: the signed
  distance of each point from the obstacle surface (positive outside the obstacle, negative =
  penetration) and the unit *outward normal of the obstacle* at the closest surface point
  (= the gradient of the signed distance);
* ``ufl_gap_normal(x, translation) -> (g, n)``: the same as UFL expressions of ``x`` (a UFL
  3-vector, normally the deformed position ``X + u``) and ``translation`` (a UFL 3-vector,
  normally a ``dolfinx.fem.Constant`` so that moving the obstacle between load steps never
  recompiles a form). Rotations are baked into the dataclass.

The signed distances are exact (rounded shapes are the Minkowski sum of a convex core and a
ball of the edge radius, so ``sdf = sdf_core - edge_radius``). Square roots and divisions are
guarded (``sqrt(max(r2, EPS**2))`` with ``EPS = 1e-12 mm``; where a normal direction is
undefined — at a sphere centre, on a capsule/cylinder axis — a fixed perpendicular unit vector
is used), so the expressions and their derivatives are finite everywhere. NumPy and UFL use
the same formulas and the same tie-breaking and agree to round-off.

Coordinate convention of the fingertip scene: finger axis along +x (distal tip at larger x),
dorsal (nail) side +z, palmar pad facing -z, y across the finger. A plate at angle theta to the
finger axis approaches the pad from -z: :func:`plate` returns the half-space below the plane
whose outward normal ``(-sin theta, 0, cos theta)`` points towards the finger.

Contact law (implemented by :func:`ufl_contact_terms`, driven by the solver)
--------------------------------------------------------------------------
Normal contact, augmented Lagrangian with nodal Uzawa updates::

    p = max(0, lambda_n - k_n * g)          [MPa]    contact pressure, >= 0
    t_N = p * n                                       traction on the tissue (n: obstacle normal)

``lambda_n`` is a scalar Function (start at 0); after each converged Newton solve the solver
sets ``lambda_n <- p`` at the nodes (:class:`UzawaUpdate`) and re-solves until the largest
penetration is <= the tolerance (0.01 mm). ``lambda_n = None`` gives the pure penalty method.
``k_n`` comes from :func:`penalty_stiffness` (tissue modulus / facet size, no per-scene
constant).

Friction, regularised Coulomb (elastic stick spring + slip limit)::

    s     = (I - n n) . [(u - u_ref) - (c - c_ref)]      tangential slip since the anchor [mm]
    t_T   = -k_t s                  if k_t |s| <= mu p     (stick)
    t_T   = -mu p s / |s|           otherwise              (slip)

with ``u_ref`` (vector Function, the displacement at the stick anchor) and ``c_ref`` (Constant,
the obstacle translation at the anchor). With ``u_ref = u`` and ``c_ref = c`` of the previous
converged load step, ``s`` is the slip increment of the step (memory-less incremental friction,
enough for monotonic loading); for stick that persists over many steps keep the anchor and move
it only where the node slipped (:func:`friction_anchor_update`). ``mu`` default 0.74 (brief §1);
``mu = 0`` gives frictionless contact and no tangential terms.

Augmented friction (optional ``lambda_t``, a vector Function of tangential multipliers, MPa)::

    v     = (I - n n) . lambda_t - k_t s
    t_T   = v                       if |v| <= mu p         (stick)
    t_T   = mu p v / |v|            otherwise              (slip)

The Uzawa update ``lambda_t <- t_T`` (with ``lambda_n <- p``) carries the stick traction in the
multiplier, so the stick creep ``|t_T - lambda_t| / k_t`` goes to zero with the updates and a
soft stick spring (a smooth Newton) no longer means soft friction. ``lambda_t = None`` is the
penalty law above.

Both laws have a kink at the Coulomb cone (|v| = mu p): the tangent jumps from k_t to the slip
branch's, and Newton can cycle between the two sides. ``friction_smoothing`` delta (0 = the
laws above) rounds the cone over the band (1 - delta) mu p < |v| < (1 + delta) mu p::

    |t_T| = |v| - (|v| - (1 - delta) mu p)^2 / (4 delta mu p)      direction v / |v|

(:func:`smoothed_cone`), which joins stick and slip with a continuous tangent. It never exceeds
mu p, equals the law above outside the band, and is at most delta/4 x mu p below it inside.

All tractions are true (Cauchy) tractions per *deformed* area: the residual is integrated over
the reference facets with Nanson's factor ``da = J |F^-T N| dA``, so the contact force is
``int p n da`` exactly as :func:`contact_metrics` reports it.

Contact outputs
---------------
:func:`contact_metrics` measures a tagged surface region. The contact area is geometric: every
boundary facet is split into four flat triangles through its deformed vertices and deformed edge
midpoints (the nodes of a P2 displacement; for P1 the midpoints are interpolated) and the gap is
evaluated at those six nodes. ``area="nodal"`` (default) counts each sub-triangle with a third of
its area per node whose gap is <= ``gap_tol_mm`` (0.01 mm default, brief §3: the lumped nodal
contact area); ``area="clip"`` interpolates the gap linearly over each sub-triangle and counts the
exact area of the part where it is <= ``gap_tol_mm`` (continuous in u, exact for a plate and an
affine displacement).

Why nodal is the default: at the edge of a real contact patch the gap has a kink (zero inside,
growing like s^(3/2) with the distance s outside), so the linearly interpolated gap between a
node in contact and a free node reaches the tolerance right next to the node in contact; the
clipped patch ends ~half an element short of the true edge all round (an O(h) deficit,
perimeter x h/2). The nodal rule puts the edge half-way between the two nodes, which is unbiased
for an edge at an unknown position between them. Measured on the fingertip at 4 N (15 deg,
docs/contact.md "Update 2 Dec 2026 (seventh session)", benchmarks/fingertip_area_rules.py):
pad element size 1.5 / 1.0 / 0.75 / 0.6 / 0.45 mm gave 176.4 / 184.1 / 183.6 / 185.6 / 186.2
mm^2 nodal against 166.7 / 176.6 / 179.5 / 182.4 / 184.7 mm^2 clipped (and 156.4 ... 179.7
mm^2 for the clipped vertex-only triangles used before). The nodal area jumps by one node's
share (~0.1 % of the patch on the fingertip's default mesh) when a node crosses the
tolerance; use ``area="clip"`` where a smooth curve matters more than the bias. Centroid,
patch length/width and the largest penetration (at the six nodes of each facet) come from the
same patch: for the nodal rule the patch is the nodes in contact plus the midpoints of the
sub-triangle edges from them to free nodes. Forces and mean pressure are integrals of the
supplied pressure over the deformed surface (quadrature); peak pressure is the largest value
at the region's vertices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from handfe.errors import InputError

EPS = 1e-12  # mm, guard for square roots and divisions by norms

Vec3 = tuple[float, float, float]


# ----------------------------------------------------------------------------- helpers


def _vec3(v: Any, name: str) -> Vec3:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be 3 finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _unit(v: Any, name: str) -> Vec3:
    a = np.asarray(_vec3(v, name))
    n = float(np.linalg.norm(a))
    if n < 1e-14:
        raise InputError(f"{name} must be a non-zero vector, got {v!r}")
    a = a / n
    return (float(a[0]), float(a[1]), float(a[2]))


def _positive(v: float, name: str, *, allow_zero: bool = False) -> float:
    v = float(v)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return v


def _perp(a: Vec3) -> Vec3:
    """A fixed unit vector perpendicular to the unit vector a."""
    av = np.asarray(a)
    e = np.eye(3)[int(np.argmin(np.abs(av)))]
    p = e - np.dot(e, av) * av
    p /= np.linalg.norm(p)
    return (float(p[0]), float(p[1]), float(p[2]))


def rotation_matrix(axis: Any, angle_deg: float) -> tuple[Vec3, Vec3, Vec3]:
    """Rotation matrix (rows) for a right-handed rotation by angle_deg about axis."""
    a = np.asarray(_unit(axis, "axis"))
    t = math.radians(float(angle_deg))
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K
    return tuple(tuple(float(c) for c in row) for row in R)  # type: ignore[return-value]


def _pts(points: np.ndarray, translation: Any | None) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim == 1:
        p = p.reshape(1, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {p.shape}")
    if translation is not None:
        p = p - np.asarray(translation, dtype=float).reshape(1, 3)
    return p


def _np_norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.einsum("ij,ij->i", v, v), EPS**2))


def _np_point_distance(v: np.ndarray, fallback: Vec3) -> tuple[np.ndarray, np.ndarray]:
    """Distance |v| and unit direction v/|v| (fallback where v = 0)."""
    d = _np_norm(v)
    ok = np.einsum("ij,ij->i", v, v) > EPS**2
    n = np.where(ok[:, None], v / d[:, None], np.asarray(fallback)[None, :])
    return d, n


def _ufl():
    import ufl

    return ufl


def extract_unique_domain(u):
    """The UFL domain of ``u``: works for Functions and for components of a mixed Function
    (``ufl.split``), which have no function space of their own."""
    from ufl.domain import extract_unique_domain as _extract

    return _extract(u)


def _u_vec(v: Vec3):
    return _ufl().as_vector([float(c) for c in v])


def _u_norm(v):
    ufl = _ufl()
    return ufl.sqrt(ufl.max_value(ufl.dot(v, v), EPS**2))


def _u_point_distance(v, fallback: Vec3):
    ufl = _ufl()
    d = _u_norm(v)
    n = ufl.conditional(ufl.gt(ufl.dot(v, v), EPS**2), v / d, _u_vec(fallback))
    return d, n


def _u_sign(s):
    ufl = _ufl()
    return ufl.conditional(ufl.ge(s, 0.0), 1.0, -1.0)


# ----------------------------------------------------------------------------- obstacles


@dataclass(frozen=True)
class HalfSpace:
    """Rigid half-space (a plate of infinite extent): the obstacle fills the side opposite to
    ``normal``. ``point`` lies on the surface, ``normal`` (any orientation, normalised here) is
    the outward normal pointing towards the tissue. gap = (x - point) . normal."""

    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", _vec3(self.point, "HalfSpace.point"))
        object.__setattr__(self, "normal", _unit(self.normal, "HalfSpace.normal"))

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        p = _pts(points, translation)
        n = np.asarray(self.normal)
        g = (p - np.asarray(self.point)) @ n
        return g, np.tile(n, (p.shape[0], 1))

    def ufl_gap_normal(self, x, translation):
        ufl = _ufl()
        n = _u_vec(self.normal)
        return ufl.dot(x - translation - _u_vec(self.point), n), n


@dataclass(frozen=True)
class Sphere:
    """Rigid ball: centre (mm), radius (mm)."""

    centre: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "Sphere.centre"))
        object.__setattr__(self, "radius", _positive(self.radius, "Sphere.radius"))

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        p = _pts(points, translation)
        d, n = _np_point_distance(p - np.asarray(self.centre), (0.0, 0.0, 1.0))
        return d - self.radius, n

    def ufl_gap_normal(self, x, translation):
        d, n = _u_point_distance(x - translation - _u_vec(self.centre), (0.0, 0.0, 1.0))
        return d - self.radius, n


@dataclass(frozen=True)
class Capsule:
    """Rigid capsule: all points within ``radius`` of the segment p0-p1 (mm)."""

    p0: Vec3 = (0.0, 0.0, -1.0)
    p1: Vec3 = (0.0, 0.0, 1.0)
    radius: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "p0", _vec3(self.p0, "Capsule.p0"))
        object.__setattr__(self, "p1", _vec3(self.p1, "Capsule.p1"))
        object.__setattr__(self, "radius", _positive(self.radius, "Capsule.radius"))
        if np.linalg.norm(np.subtract(self.p1, self.p0)) < 1e-9:
            raise InputError("Capsule.p0 and Capsule.p1 must differ (use a Sphere)")

    @property
    def _axis(self) -> Vec3:
        return _unit(np.subtract(self.p1, self.p0), "Capsule axis")

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        p = _pts(points, translation)
        p0 = np.asarray(self.p0)
        d = np.asarray(self.p1) - p0
        t = np.clip((p - p0) @ d / float(d @ d), 0.0, 1.0)
        v = p - p0 - t[:, None] * d
        dist, n = _np_point_distance(v, _perp(self._axis))
        return dist - self.radius, n

    def ufl_gap_normal(self, x, translation):
        ufl = _ufl()
        p0 = _u_vec(self.p0)
        dn = np.subtract(self.p1, self.p0)
        d = _u_vec(tuple(dn))
        t = ufl.min_value(ufl.max_value(ufl.dot(x - translation - p0, d) / float(dn @ dn), 0.0),
                          1.0)
        v = x - translation - p0 - t * d
        dist, n = _u_point_distance(v, _perp(self._axis))
        return dist - self.radius, n


@dataclass(frozen=True)
class Cylinder:
    """Finite rigid cylinder: centre, axis (normalised here), radius, half_length (mm, along the
    axis) and ``edge_radius`` (mm) rounding the two circular rims (0 = sharp,
    = radius gives hemispherical ends, i.e. a capsule)."""

    centre: Vec3 = (0.0, 0.0, 0.0)
    axis: Vec3 = (0.0, 0.0, 1.0)
    radius: float = 1.0
    half_length: float = 1.0
    edge_radius: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "Cylinder.centre"))
        object.__setattr__(self, "axis", _unit(self.axis, "Cylinder.axis"))
        object.__setattr__(self, "radius", _positive(self.radius, "Cylinder.radius"))
        object.__setattr__(self, "half_length",
                           _positive(self.half_length, "Cylinder.half_length"))
        object.__setattr__(self, "edge_radius",
                           _positive(self.edge_radius, "Cylinder.edge_radius", allow_zero=True))
        if self.edge_radius > min(self.radius, self.half_length):
            raise InputError(f"Cylinder.edge_radius {self.edge_radius} must be <= radius "
                             f"{self.radius} and <= half_length {self.half_length}")

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        p = _pts(points, translation) - np.asarray(self.centre)
        a = np.asarray(self.axis)
        s = p @ a
        rv = p - s[:, None] * a
        rho, er = _np_point_distance(rv, _perp(self.axis))
        sg = np.where(s >= 0.0, 1.0, -1.0)
        dr = rho - (self.radius - self.edge_radius)
        ds = np.abs(s) - (self.half_length - self.edge_radius)
        m = np.maximum(dr, ds)
        qr, qs = np.maximum(dr, 0.0), np.maximum(ds, 0.0)
        qn = np.sqrt(np.maximum(qr * qr + qs * qs, EPS**2))
        g = np.where(m > 0.0, qn, 0.0) + np.minimum(m, 0.0) - self.edge_radius
        n_out = (qr[:, None] * er + (qs * sg)[:, None] * a) / qn[:, None]
        n_in = np.where((dr > ds)[:, None], er, sg[:, None] * a)
        n = np.where((m > EPS)[:, None], n_out, n_in)
        return g, n

    def ufl_gap_normal(self, x, translation):
        ufl = _ufl()
        p = x - translation - _u_vec(self.centre)
        a = _u_vec(self.axis)
        s = ufl.dot(p, a)
        rho, er = _u_point_distance(p - s * a, _perp(self.axis))
        sg = _u_sign(s)
        dr = rho - (self.radius - self.edge_radius)
        ds = abs(s) - (self.half_length - self.edge_radius)
        m = ufl.max_value(dr, ds)
        qr, qs = ufl.max_value(dr, 0.0), ufl.max_value(ds, 0.0)
        qn = ufl.sqrt(ufl.max_value(qr * qr + qs * qs, EPS**2))
        g = ufl.conditional(ufl.gt(m, 0.0), qn, 0.0) + ufl.min_value(m, 0.0) - self.edge_radius
        n_out = (qr * er + qs * sg * a) / qn
        n_in = ufl.conditional(ufl.gt(dr, ds), er, sg * a)
        return g, ufl.conditional(ufl.gt(m, EPS), n_out, n_in)


_IDENTITY: tuple[Vec3, Vec3, Vec3] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class RoundedBox:
    """Rigid box with rounded edges: centre, half_sizes (mm, in the box frame), rotation (3x3,
    rows; maps box-frame vectors to world: x = centre + R @ x_box) and edge_radius (mm)."""

    centre: Vec3 = (0.0, 0.0, 0.0)
    half_sizes: Vec3 = (1.0, 1.0, 1.0)
    rotation: tuple[Vec3, Vec3, Vec3] = _IDENTITY
    edge_radius: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "RoundedBox.centre"))
        h = _vec3(self.half_sizes, "RoundedBox.half_sizes")
        if min(h) <= 0:
            raise InputError(f"RoundedBox.half_sizes must be > 0, got {h}")
        object.__setattr__(self, "half_sizes", h)
        R = np.asarray(self.rotation, dtype=float)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9) \
                or np.linalg.det(R) < 0:
            raise InputError(f"RoundedBox.rotation must be a 3x3 rotation matrix, got {R}")
        object.__setattr__(self, "rotation", tuple(tuple(float(c) for c in r) for r in R))
        object.__setattr__(self, "edge_radius",
                           _positive(self.edge_radius, "RoundedBox.edge_radius", allow_zero=True))
        if self.edge_radius > min(h):
            raise InputError(f"RoundedBox.edge_radius {self.edge_radius} must be <= the "
                             f"smallest half size {min(h)}")

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        R = np.asarray(self.rotation)
        p = (_pts(points, translation) - np.asarray(self.centre)) @ R  # box frame: R^T (x - c)
        sg = np.where(p >= 0.0, 1.0, -1.0)
        q = np.abs(p) - (np.asarray(self.half_sizes) - self.edge_radius)
        m = q.max(axis=1)
        qp = np.maximum(q, 0.0)
        qn = np.sqrt(np.maximum((qp * qp).sum(axis=1), EPS**2))
        g = np.where(m > 0.0, qn, 0.0) + np.minimum(m, 0.0) - self.edge_radius
        n_out = sg * qp / qn[:, None]
        k = np.argmax(q, axis=1)
        n_in = np.zeros_like(p)
        n_in[np.arange(p.shape[0]), k] = sg[np.arange(p.shape[0]), k]
        n_loc = np.where((m > EPS)[:, None], n_out, n_in)
        return g, n_loc @ R.T

    def ufl_gap_normal(self, x, translation):
        ufl = _ufl()
        R = ufl.as_matrix([[float(c) for c in r] for r in self.rotation])
        p = R.T * (x - translation - _u_vec(self.centre))
        h = [hi - self.edge_radius for hi in self.half_sizes]
        q = [abs(p[i]) - h[i] for i in range(3)]
        sg = [_u_sign(p[i]) for i in range(3)]
        m = ufl.max_value(ufl.max_value(q[0], q[1]), q[2])
        qp = [ufl.max_value(qi, 0.0) for qi in q]
        qn = ufl.sqrt(ufl.max_value(qp[0] ** 2 + qp[1] ** 2 + qp[2] ** 2, EPS**2))
        g = ufl.conditional(ufl.gt(m, 0.0), qn, 0.0) + ufl.min_value(m, 0.0) - self.edge_radius
        n_out = ufl.as_vector([sg[i] * qp[i] / qn for i in range(3)])
        e = [ufl.as_vector([sg[i] if j == i else 0.0 for j in range(3)]) for i in range(3)]
        # argmax with the first maximum winning (as numpy.argmax)
        n_in = ufl.conditional(ufl.And(ufl.ge(q[0], q[1]), ufl.ge(q[0], q[2])), e[0],
                               ufl.conditional(ufl.ge(q[1], q[2]), e[1], e[2]))
        n_loc = ufl.conditional(ufl.gt(m, EPS), n_out, n_in)
        return g, R * n_loc


@dataclass(frozen=True)
class Union:
    """Union of obstacles: gap = min over the parts, normal of the part giving the minimum
    (the first one on ties)."""

    parts: tuple = field(default_factory=tuple)

    def __post_init__(self) -> None:
        parts = tuple(self.parts)
        if not parts:
            raise InputError("Union needs at least one obstacle")
        for p in parts:
            if not hasattr(p, "gap_normal") or not hasattr(p, "ufl_gap_normal"):
                raise InputError(f"Union part {p!r} is not an obstacle")
        object.__setattr__(self, "parts", parts)

    def gap_normal(self, points: np.ndarray, translation: Any | None = None):
        g, n = self.parts[0].gap_normal(points, translation)
        for part in self.parts[1:]:
            gi, ni = part.gap_normal(points, translation)
            closer = gi < g
            n = np.where(closer[:, None], ni, n)
            g = np.where(closer, gi, g)
        return g, n

    def ufl_gap_normal(self, x, translation):
        ufl = _ufl()
        g, n = self.parts[0].ufl_gap_normal(x, translation)
        for part in self.parts[1:]:
            gi, ni = part.ufl_gap_normal(x, translation)
            n = ufl.conditional(ufl.lt(gi, g), ni, n)
            g = ufl.min_value(g, gi)
        return g, n


Obstacle = HalfSpace | Sphere | Capsule | Cylinder | RoundedBox | Union


def plate(theta_deg: float, point: Any = (0.0, 0.0, 0.0)) -> HalfSpace:
    """Flat plate at angle theta (deg, 0..90) to the finger axis (+x), below the palmar pad:
    outward normal (-sin theta, 0, cos theta) points towards the finger; ``point`` lies on the
    plate surface. Push it into the pad by translating along that normal."""
    t = float(theta_deg)
    if not (0.0 <= t <= 90.0):
        raise InputError(f"plate angle must be within 0..90 deg, got {theta_deg!r}")
    r = math.radians(t)
    return HalfSpace(point=point, normal=(-math.sin(r), 0.0, math.cos(r)))


# ----------------------------------------------------------------------------- contact law


def penalty_stiffness(E_eff_MPa: float, h_mm: float, factor: float = 10.0) -> float:
    """Normal penalty k_n = factor * E_eff / h  [N/mm^3 = MPa/mm].

    E_eff_MPa: small-strain Young's modulus of the tissue at the contact (e.g. 2 mu (1 + nu)
    of the outer layer); h_mm: facet size on the contact surface. factor = 10 makes the
    penalty layer ~10x stiffer than one element of tissue; the Uzawa iterations then remove
    the remaining penetration, so the result does not depend on the factor."""
    E = _positive(E_eff_MPa, "E_eff_MPa")
    h = _positive(h_mm, "h_mm")
    f = _positive(factor, "factor")
    return f * E / h


@dataclass
class ContactTerms:
    """UFL pieces of the contact contribution (see the module docstring for the law).

    residual: add to the tissue residual R(u; v) = internal - external (it equals
    ``-int (p n + t_T) . v da`` on the contact measure); its Jacobian comes from
    ``ufl.derivative``. gap [mm], normal, pressure [MPa] (>= 0), tangential_traction [MPa]
    (zero vector if frictionless) and area_factor (J |F^-T N|, deformed/reference area) are
    expressions for output and for the Uzawa update. With friction, slip [mm] (tangential slip
    since the anchor) and trial_traction [MPa] (before the return mapping onto mu p) too, else
    None."""

    residual: Any
    gap: Any
    normal: Any
    pressure: Any
    tangential_traction: Any
    area_factor: Any
    lambda_n: Any = None
    slip: Any = None
    trial_traction: Any = None


def deformed_area_factor(u):
    """Nanson's factor J |F^-T N| (deformed area per reference area) on exterior facets."""
    ufl = _ufl()
    dim = len(u)
    F = ufl.Identity(dim) + ufl.grad(u)
    N = ufl.FacetNormal(extract_unique_domain(u))
    cof = ufl.det(F) * ufl.inv(F).T * N
    return ufl.sqrt(ufl.dot(cof, cof))


def smoothed_cone(trial, limit, smoothing: Any = 0.0):
    """Traction of the return mapping of ``trial`` (vector) onto the disc of radius ``limit``
    (= mu p, MPa), with the cone rounded over ``smoothing`` delta (see the module docstring;
    the Python float 0 gives the sharp law). UFL in, UFL out."""
    ufl = _ufl()
    t = ufl.sqrt(ufl.max_value(ufl.dot(trial, trial), EPS**2))
    slip = limit * trial / t
    if isinstance(smoothing, int | float) and float(smoothing) == 0.0:
        return ufl.conditional(ufl.gt(t, limit), slip, trial)
    lo = (1.0 - smoothing) * limit
    # the blend is only taken for lo < t <= hi, where limit > 0; the guard keeps the unused
    # branch finite where limit = 0
    blend = (t - (t - lo) ** 2 / ufl.max_value(4.0 * smoothing * limit, EPS)) * trial / t
    return ufl.conditional(ufl.gt(t, (1.0 + smoothing) * limit), slip,
                           ufl.conditional(ufl.gt(t, lo), blend, trial))


def ufl_contact_terms(u, v, obstacle, translation, ds_c, *, k_n, lambda_n=None,
                      mu: Any = 0.0, k_t: Any = None, u_ref=None,
                      translation_ref=None, lambda_t=None,
                      friction_smoothing: Any = 0.0) -> ContactTerms:
    """Contact residual contribution for the tissue displacement ``u`` (vector Function, mm),
    test function ``v``, a rigid ``obstacle`` translated by ``translation`` (Constant, mm), on
    the measure ``ds_c`` (e.g. ``ds(tag)``; set its quadrature degree in the metadata).

    k_n: normal penalty [N/mm^3] (Constant or float; use a Constant to change it without
    recompiling). lambda_n: scalar Function of Uzawa multipliers [MPa] or None (penalty only).
    mu: friction coefficient (float or Constant; the Python float 0 switches friction off).
    k_t: tangential stick stiffness [N/mm^3] (default k_n). u_ref: vector Function, the
    displacement at the stick anchor (previous converged step for incremental friction);
    translation_ref: Constant, the obstacle translation at the anchor. lambda_t: vector
    Function of tangential Uzawa multipliers [MPa] (augmented friction) or None.
    friction_smoothing: relative width delta of the rounded Coulomb cone (float or Constant;
    the Python float 0 = sharp cone; :func:`smoothed_cone`)."""
    ufl = _ufl()
    X = ufl.SpatialCoordinate(extract_unique_domain(u))
    x = X + u
    g, n = obstacle.ufl_gap_normal(x, translation)
    lam = 0.0 if lambda_n is None else lambda_n
    p = ufl.max_value(lam - k_n * g, 0.0)
    area = deformed_area_factor(u)
    frictionless = isinstance(mu, int | float) and float(mu) == 0.0
    s = trial = None
    if frictionless:
        tT = ufl.as_vector([0.0] * len(u))
    else:
        if u_ref is None or translation_ref is None:
            raise InputError("friction (mu > 0) needs u_ref (Function) and translation_ref "
                             "(Constant): the stick anchor")
        kt = k_n if k_t is None else k_t
        Pt = ufl.Identity(len(u)) - ufl.outer(n, n)
        s = Pt * ((u - u_ref) - (translation - translation_ref))
        limit = mu * p
        trial = -kt * s if lambda_t is None else Pt * lambda_t - kt * s
        tT = smoothed_cone(trial, limit, friction_smoothing)
    residual = -ufl.inner(p * n + tT, v) * area * ds_c
    return ContactTerms(residual=residual, gap=g, normal=n, pressure=p,
                        tangential_traction=tT, area_factor=area, lambda_n=lambda_n,
                        slip=s, trial_traction=trial)


def assemble_nodal(form) -> np.ndarray:
    """Assemble a linear form and return its values at this rank's dofs, ghosts included
    (owners' sums), laid out as the ``x.array`` of a Function on the form's space."""
    from dolfinx.fem import petsc as fem_petsc
    from petsc4py import PETSc

    b = fem_petsc.assemble_vector(form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    with b.localForm() as loc:
        arr = loc.array.copy()
    b.destroy()
    return arr


class UzawaUpdate:
    """Nodal Uzawa update ``lambda_n <- p = max(0, lambda_n - k_n g)`` (compiled once).

    Call after each converged Newton solve; returns ``(max_change_MPa, max_penetration_mm)``
    over all ranks, both evaluated at the dofs of ``lambda_n`` that lie on the contact
    facets (``facets``: indices of the candidate contact facets, e.g. ``facet_tags.find(pad)``).
    Dofs off those facets are set to zero."""

    def __init__(self, terms: ContactTerms, facets: np.ndarray, ds_c: Any | None = None,
                 k_n: Any | None = None):
        """``ds_c``, ``k_n``: the contact measure of ``terms`` (with its quadrature) and their
        normal penalty Constant; given both, :meth:`rescale` keeps the nodal contact forces
        (not only the nodal pressures) of the state."""
        import ufl
        from dolfinx import fem

        if terms.lambda_n is None:
            raise InputError("UzawaUpdate needs ufl_contact_terms(..., lambda_n=Function)")
        lam = terms.lambda_n
        V = lam.function_space
        self._lam = lam
        pts = V.element.interpolation_points()
        self._p = fem.Expression(terms.pressure, pts)
        self._g = fem.Expression(terms.gap, pts)
        mesh = V.mesh
        fdim = mesh.topology.dim - 1
        self._dofs = fem.locate_dofs_topological(V, fdim, np.asarray(facets, dtype=np.int32))
        self._pfun = fem.Function(V)
        self._gfun = fem.Function(V)
        self._comm = mesh.comm
        self._force_forms = None
        self._k = k_n
        if ds_c is not None and k_n is not None:
            q = ufl.TestFunction(V)
            p, a = terms.pressure, terms.area_factor
            # nodal normal force and its derivative by lambda (the active part of the lumped
            # facet mass), both as the contact residual integrates them
            self._force_forms = (
                fem.form(p * a * q * ds_c),
                fem.form(ufl.conditional(ufl.gt(p, 0.0), 1.0, 0.0) * a * q * ds_c),
                fem.form(a * q * ds_c))

    def penetration(self) -> float:
        """Largest penetration (mm) at the multiplier dofs, over all ranks, without updating."""
        from mpi4py import MPI

        self._gfun.interpolate(self._g)
        pen = float(np.max(-self._gfun.x.array[self._dofs], initial=0.0))
        return max(0.0, self._comm.allreduce(pen, op=MPI.MAX))

    def peak_pressure(self) -> float:
        """Largest nodal contact pressure (MPa) of the current state, over all ranks."""
        from mpi4py import MPI

        self._pfun.interpolate(self._p)
        p = float(np.max(self._pfun.x.array[self._dofs], initial=0.0))
        return max(0.0, self._comm.allreduce(p, op=MPI.MAX))

    def rescale(self, k_old: float, k_new: float, *, match_forces: bool = True,
                rtol: float = 1e-3, max_iterations: int = 30) -> float:
        """Multipliers for a normal penalty changed from ``k_old`` to ``k_new`` (MPa/mm) that
        keep the contact tractions of the current state; only the stiffness of what follows
        changes. First every node's trial pressure ``lambda - k g`` is kept: lambda +=
        (k_new - k_old) g; a node with a gap (g >= 0) and no pressure gets lambda = 0, so its
        force starts at contact (a positive multiplier there would push before touching).
        That is exact where the gap is linear over a facet (vertex quadrature, a flat obstacle).
        With Gauss points on a curved obstacle the facet's interior is deeper than its nodes by
        the sagitta, and the pressure there grows with k: on a P1 block pressed 0.08 mm into a
        5 mm ball (0.5 mm facets, ``tests/test_friction.py``) x4 raised the normal force by 30 %.
        So, given the contact measure (and ``match_forces``), Jacobi sweeps then match each
        node's normal force (int p J|F^-T N| phi_i da) to its value before, to ``rtol`` of the
        largest, in at most ``max_iterations`` assemblies over the contact facets; the penalty
        Constant is then ``k_new``. Returns the largest nodal-force mismatch left, relative to
        the largest nodal force (0 without the contact measure: the caller sets the penalty)."""
        from mpi4py import MPI

        nodal = assemble_nodal
        d = self._dofs
        f_old = (nodal(self._force_forms[0])[d] if match_forces and self._force_forms
                 else None)
        self._gfun.interpolate(self._g)
        lam = self._lam.x.array
        g = self._gfun.x.array[d]
        keep = (lam[d] - k_old * g > 0.0) | (g < 0.0)
        lam[d] = np.where(keep, lam[d] + (k_new - k_old) * g, 0.0)
        self._lam.x.scatter_forward()
        if f_old is None:
            return 0.0
        self._k.value = k_new
        scale = self._comm.allreduce(float(np.abs(f_old).max(initial=0.0)), op=MPI.MAX)
        if scale <= 0.0:
            return 0.0
        m0 = nodal(self._force_forms[2])[d]
        off = float("inf")
        for _ in range(max_iterations):
            df = f_old - nodal(self._force_forms[0])[d]
            off = self._comm.allreduce(float(np.abs(df).max(initial=0.0)), op=MPI.MAX) / scale
            if off <= rtol:
                break
            m = nodal(self._force_forms[1])[d]
            # a node without an active point (then df >= 0): its whole facet mass
            m = np.where(m > 1e-12 * m0, m, m0)
            lam[d] += np.where(m > 0.0, df / np.where(m > 0.0, m, 1.0), 0.0)
            self._lam.x.scatter_forward()
        return off

    def __call__(self) -> tuple[float, float]:
        from mpi4py import MPI

        self._pfun.interpolate(self._p)
        self._gfun.interpolate(self._g)
        lam = self._lam.x.array
        new = np.zeros_like(lam)
        d = self._dofs
        new[d] = self._pfun.x.array[d]
        change = float(np.max(np.abs(new[d] - lam[d]), initial=0.0))
        pen = float(np.max(-self._gfun.x.array[d], initial=0.0))
        lam[:] = new
        self._lam.x.scatter_forward()
        return (self._comm.allreduce(change, op=MPI.MAX),
                max(0.0, self._comm.allreduce(pen, op=MPI.MAX)))


def friction_anchor_update(s_T: np.ndarray, pressure: np.ndarray, mu: float,
                           k_t: float, margin: float = 1.0) -> np.ndarray:
    """Return-mapping for the stick anchor, nodal NumPy arrays: given the tangential slip
    ``s_T`` (n, 3) since the anchor and the pressure (n,) at converged state, return the shift
    to add to ``u_ref``. Nodes that stuck (k_t |s| <= mu p) are not moved; nodes that slipped
    keep the elastic slip ``margin * mu p / k_t`` along s/|s| (``margin`` > 1 keeps the
    quadrature points between slipping nodes in the slip branch, so the traction stays
    exactly mu p there); nodes out of contact (p = 0) follow the surface."""
    s = np.asarray(s_T, dtype=float)
    ns = np.sqrt(np.maximum(np.einsum("ij,ij->i", s, s), EPS**2))
    limit = mu * np.maximum(pressure, 0.0) / k_t
    keep = np.where(ns <= limit, ns, np.minimum(ns, margin * limit))
    return s - s * (keep / ns)[:, None]


# ----------------------------------------------------------------------------- outputs


@dataclass(frozen=True)
class ContactMetrics:
    """Contact outputs of one tagged surface region (see :func:`contact_metrics`).

    Forces in N, area in mm^2, pressures in kPa, lengths in mm. Quantities that need the
    pressure are NaN when no pressure was given; centroid is NaN when the area is 0.
    min_gap_mm: smallest gap at the region's deformed facet nodes (vertices and edge
    midpoints; negative = penetration; at u = 0 it is the plate travel to first contact);
    max_penetration_mm = max(0, -min_gap_mm).
    length_mm/width_mm: extent of the patch along the first/second axis."""

    normal_force_N: float
    tangential_force_N: float
    contact_area_mm2: float
    mean_pressure_kPa: float
    peak_pressure_kPa: float
    centroid_mm: tuple[float, float, float]
    length_mm: float
    width_mm: float
    max_penetration_mm: float
    force_vector_N: tuple[float, float, float]
    gap_tol_mm: float
    min_gap_mm: float = float("nan")

    def as_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def _owned_tagged_facets(mesh, facet_tags, tag: int) -> np.ndarray:
    fdim = mesh.topology.dim - 1
    mesh.topology.create_entities(fdim)
    n_owned = mesh.topology.index_map(fdim).size_local
    f = np.asarray(facet_tags.find(int(tag)), dtype=np.int32)
    return f[f < n_owned]


def _node_values(fun, mesh) -> np.ndarray:
    """Values of a P1 Function at the geometry nodes: (n_nodes, bs)."""
    V = fun.function_space
    bs = V.dofmap.index_map_bs
    geo = mesh.geometry.dofmap.array.reshape(-1, len(mesh.geometry.dofmap.links(0)))
    dofs = V.dofmap.list.array.reshape(geo.shape[0], -1)
    nvert = dofs.shape[1]
    out = np.zeros((mesh.geometry.x.shape[0], bs))
    arr = fun.x.array.reshape(-1, bs)
    out[geo[:, :nvert].reshape(-1)] = arr[dofs.reshape(-1)]
    return out


def _to_p1(expr_or_fun, mesh, shape: tuple[int, ...]):
    """Interpolate a Function or a UFL expression into P1 (vector if shape == (3,))."""
    from dolfinx import fem

    if shape:
        V1 = fem.VectorFunctionSpace(mesh, ("CG", 1))
    else:
        V1 = fem.FunctionSpace(mesh, ("CG", 1))
    f1 = fem.Function(V1)
    if isinstance(expr_or_fun, fem.Function):
        f1.interpolate(expr_or_fun)
    else:
        f1.interpolate(fem.Expression(expr_or_fun, V1.element.interpolation_points()))
    return f1


def _clip_patch(x: np.ndarray, phi: np.ndarray, axes: np.ndarray):
    """Part of flat triangles (nf, 3, 3) where the linearly interpolated phi (nf, 3) <= 0:
    returns area (nf,), area*centroid (nf, 3), and min/max projection on the axes (2,)."""
    e1 = x[:, 1] - x[:, 0]
    e2 = x[:, 2] - x[:, 0]
    A = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    C = x.mean(axis=1)
    inside = phi <= 0.0
    ni = inside.sum(axis=1)
    area = np.where(ni == 3, A, 0.0)
    mom = area[:, None] * C
    pts = [x[inside]]  # inside vertices
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        for j in (a, b):  # crossing points on edges with a sign change
            cross = inside[:, k] & ~inside[:, j]
            if np.any(cross):
                t = phi[cross, k] / (phi[cross, k] - phi[cross, j])
                pts.append(x[cross, k] + t[:, None] * (x[cross, j] - x[cross, k]))
        # corner triangle at vertex k: fractions along k->a and k->b
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = phi[:, k] / (phi[:, k] - phi[:, a])
            tb = phi[:, k] / (phi[:, k] - phi[:, b])
        one_in = (ni == 1) & inside[:, k]
        if np.any(one_in):
            s = one_in
            pa = x[s, k] + ta[s, None] * (x[s, a] - x[s, k])
            pb = x[s, k] + tb[s, None] * (x[s, b] - x[s, k])
            ar = A[s] * ta[s] * tb[s]
            area[s] = ar
            mom[s] = ar[:, None] * (x[s, k] + pa + pb) / 3.0
        one_out = (ni == 2) & ~inside[:, k]
        if np.any(one_out):
            s = one_out
            pa = x[s, k] + ta[s, None] * (x[s, a] - x[s, k])
            pb = x[s, k] + tb[s, None] * (x[s, b] - x[s, k])
            ar = A[s] * ta[s] * tb[s]
            area[s] = A[s] - ar
            mom[s] = A[s, None] * C[s] - ar[:, None] * (x[s, k] + pa + pb) / 3.0
    P = np.concatenate(pts, axis=0) if pts else np.zeros((0, 3))
    proj = P @ axes.T  # (n, 2)
    lo = proj.min(axis=0) if proj.shape[0] else np.full(2, np.inf)
    hi = proj.max(axis=0) if proj.shape[0] else np.full(2, -np.inf)
    return area, mom, lo, hi


AREA_METHODS = ("nodal", "clip")


def _nodal_patch(x: np.ndarray, phi: np.ndarray, axes: np.ndarray):
    """Lumped nodal patch of flat triangles (nf, 3, 3) with nodes in contact where phi <= 0:
    each triangle counts a third of its area per node in contact. Returns area (nf,),
    area*centroid (nf, 3) and min/max projection on the axes (2,) of the patch (the nodes in
    contact and the midpoints of the edges from them to free nodes)."""
    A = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    inside = phi <= 0.0
    area = A * inside.sum(axis=1) / 3.0
    mom = (A[:, None, None] / 3.0 * x * inside[..., None]).sum(axis=1)
    pts = [x[inside]]
    for k in range(3):
        j = (k + 1) % 3
        cross = inside[:, k] != inside[:, j]
        if np.any(cross):
            pts.append(0.5 * (x[cross, k] + x[cross, j]))
    proj = np.concatenate(pts, axis=0) @ axes.T
    lo = proj.min(axis=0) if proj.shape[0] else np.full(2, np.inf)
    hi = proj.max(axis=0) if proj.shape[0] else np.full(2, -np.inf)
    return area, mom, lo, hi


#: the four sub-triangles of a facet whose six nodes are (v0, v1, v2, m01, m12, m20): the
#: corner triangles v0 m01 m20, m01 v1 m12, m20 m12 v2 and the centre m01 m12 m20
SUBTRIANGLES = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])


def _facet_nodes(u, facets: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Deformed positions X + u (nf, 6, 3) of the boundary facets ``facets`` (owned,
    exterior; ``nodes`` their vertex geometry indices, (nf, 3)): the three vertices, then the
    midpoints of edges 01, 12, 20 (u evaluated in the facet's cell, so a P2 displacement's
    mid-edge values are used)."""
    mesh = u.function_space.mesh
    fdim = mesh.topology.dim - 1
    if facets.size == 0:
        return np.zeros((0, 6, 3))
    mesh.topology.create_connectivity(fdim, fdim + 1)
    f2c = mesh.topology.connectivity(fdim, fdim + 1)
    cells = np.array([f2c.links(f)[0] for f in facets], dtype=np.int32)
    Xv = mesh.geometry.x[:, :3][nodes]
    X = np.concatenate([Xv, 0.5 * (Xv + Xv[:, [1, 2, 0]])], axis=1)
    vals = u.eval(np.ascontiguousarray(X.reshape(-1, 3)), np.repeat(cells, 6))
    return X + np.asarray(vals).reshape(X.shape)


def mirrored_total(v, symmetry_normal) -> np.ndarray:
    """The whole body's value of a vector integral ``v`` over one half of a body symmetric
    about the plane through the origin with normal ``symmetry_normal``: twice ``v`` with its
    normal component cancelled (the mirror half adds the reflected vector)."""
    e = np.asarray(_unit(symmetry_normal, "symmetry_normal"))
    v = np.asarray(v, dtype=float)
    return 2.0 * (v - (v @ e) * e)


def contact_metrics(u, obstacle, translation_value, facet_tags, tag: int, *,
                    gap_tol_mm: float = 0.01, pressure=None, tangential_traction=None,
                    axes=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), comm=None,
                    quadrature_degree: int = 4, metadata: dict | None = None,
                    symmetry_normal=None, area: str = "nodal") -> ContactMetrics:
    """Contact outputs of the surface region ``facet_tags == tag`` for the displacement ``u``
    (vector Function, mm) against ``obstacle`` translated by ``translation_value`` (3 floats).

    * contact area: every facet split into four flat triangles through X + u at its vertices
      and edge midpoints; ``area="nodal"``: a third of a sub-triangle's area per node with
      gap <= gap_tol_mm (lumped nodal area; unbiased at the kink of the gap at a patch edge);
      ``area="clip"``: the exact area where the linearly interpolated gap <= gap_tol_mm
      (continuous in u; exact for a plate and an affine u). Module docstring: why and numbers.
    * centroid (area-weighted), length/width = extent of that patch along ``axes[0]``
      and ``axes[1]`` (normalised), max_penetration_mm = max(0, -gap) at the six nodes of
      the region's facets.
    * pressure (MPa; UFL expression or Function, e.g. ``ContactTerms.pressure``): force vector
      ``int p n da`` over the region (deformed area, n = obstacle normal, quadrature degree
      ``quadrature_degree``, or the rule ``metadata``), normal_force_N = its magnitude, mean
      pressure = ``int p da`` /
      contact area, peak = max of p at the region's vertices (interpolated to P1).
    * tangential_traction (MPa vector expression, e.g. ``ContactTerms.tangential_traction``):
      tangential_force_N = |int t_T da|; 0 if None and a pressure is given.

    * symmetry_normal (3 floats): the mesh is one half of a body (and load) symmetric about the
      plane through the origin with this normal; the outputs are the whole body's (areas and
      force integrals doubled with their normal component cancelled, the patch mirrored for
      the extents; each axis must lie in or across the plane).

    Every facet is counted once over MPI ranks (owned facets only) and all numbers are reduced
    with ``comm.allreduce``; the result is the same on every rank."""
    import ufl
    from dolfinx import cpp, fem
    from mpi4py import MPI

    mesh = u.function_space.mesh
    comm = mesh.comm if comm is None else comm
    tol = _positive(gap_tol_mm, "gap_tol_mm", allow_zero=True)
    ax = np.array([_unit(a, "axes[i]") for a in axes])
    if ax.shape != (2, 3):
        raise InputError(f"axes must be two 3-vectors, got {axes!r}")
    t_val = np.asarray(_vec3(translation_value, "translation_value"))
    fdim = mesh.topology.dim - 1

    if area not in AREA_METHODS:
        raise InputError(f"area method {area!r}: use one of {', '.join(AREA_METHODS)}")

    facets = _owned_tagged_facets(mesh, facet_tags, tag)
    nodes = cpp.mesh.entities_to_geometry(mesh._mesh, fdim, facets, False)[:, :3] \
        if facets.size else np.zeros((0, 3), dtype=np.int32)
    xf = _facet_nodes(u, facets, nodes)[:, SUBTRIANGLES].reshape(-1, 3, 3)  # (4 nf, 3, 3)
    g, _ = obstacle.gap_normal(xf.reshape(-1, 3), t_val)
    g = g.reshape(-1, 3)
    patch = _nodal_patch if area == "nodal" else _clip_patch
    area_f, mom_f, lo, hi = patch(xf, g - tol, ax)
    area_mm2 = comm.allreduce(float(area_f.sum()), op=MPI.SUM)
    mom = np.array([comm.allreduce(float(c), op=MPI.SUM) for c in mom_f.sum(axis=0)])
    lo = np.array([comm.allreduce(float(c), op=MPI.MIN) for c in lo])
    hi = np.array([comm.allreduce(float(c), op=MPI.MAX) for c in hi])
    if symmetry_normal is not None:
        e = np.asarray(_unit(symmetry_normal, "symmetry_normal"))
        area_mm2 *= 2.0
        mom = mirrored_total(mom, e)
        for k in range(2):
            d = float(ax[k] @ e)
            if abs(abs(d) - 1.0) < 1e-9 and hi[k] >= lo[k]:  # across the plane
                lo[k], hi[k] = min(lo[k], -hi[k]), max(hi[k], -lo[k])
            elif abs(d) > 1e-9:
                raise InputError(f"axis {tuple(ax[k])} is neither in nor across the symmetry "
                                 f"plane (normal {tuple(e)})")
    ext = np.where(hi >= lo, hi - lo, 0.0)
    gmin = comm.allreduce(float(np.min(g, initial=np.inf)), op=MPI.MIN)
    pen = max(0.0, -gmin) if np.isfinite(gmin) else 0.0
    centroid = tuple(float(c) for c in (mom / area_mm2 if area_mm2 > 0 else np.full(3, np.nan)))

    nan = float("nan")
    fvec = (nan, nan, nan)
    fn = ft = pmean = ppeak = nan
    if pressure is not None:
        tr = fem.Constant(mesh, t_val)
        X = ufl.SpatialCoordinate(mesh)
        _, n = obstacle.ufl_gap_normal(X + u, tr)
        da = deformed_area_factor(u)
        c = fem.Constant(mesh, np.zeros(7))
        integrand = pressure * (c[0] + c[1] * n[0] + c[2] * n[1] + c[3] * n[2])
        if tangential_traction is not None:
            integrand = integrand + (c[4] * tangential_traction[0]
                                     + c[5] * tangential_traction[1]
                                     + c[6] * tangential_traction[2])
        dsm = ufl.Measure("ds", domain=mesh, subdomain_data=facet_tags,
                          metadata=metadata or {"quadrature_degree": int(quadrature_degree)})
        form = fem.form(integrand * da * dsm(int(tag)))
        vals = []
        for i in range(7 if tangential_traction is not None else 4):
            c.value = np.eye(7)[i]
            vals.append(comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM))
        psum = vals[0]
        fv, tv = np.array(vals[1:4]), np.array(vals[4:7]) if len(vals) > 4 else np.zeros(3)
        if symmetry_normal is not None:
            psum, fv, tv = 2.0 * psum, mirrored_total(fv, e), mirrored_total(tv, e)
        fvec = tuple(float(v) for v in fv)
        fn = float(np.linalg.norm(fvec))
        ft = float(np.linalg.norm(tv)) if tangential_traction is not None else 0.0
        pmean = 1e3 * psum / area_mm2 if area_mm2 > 0 else 0.0
        p1 = _to_p1(pressure, mesh, ())
        pv = _node_values(p1, mesh)[:, 0][nodes]
        ppeak = 1e3 * comm.allreduce(float(np.max(pv, initial=0.0)), op=MPI.MAX)
    return ContactMetrics(normal_force_N=fn, tangential_force_N=ft, contact_area_mm2=area_mm2,
                          mean_pressure_kPa=pmean, peak_pressure_kPa=ppeak,
                          centroid_mm=centroid, length_mm=float(ext[0]),
                          width_mm=float(ext[1]), max_penetration_mm=pen,
                          force_vector_N=fvec, gap_tol_mm=tol,
                          min_gap_mm=gmin if np.isfinite(gmin) else float("nan"))

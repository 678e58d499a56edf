"""A Newton line-search pre-check that shortens a step before it inverts cells.

PETSc's backtracking line search only sees the residual norm, and full steps (``basic``) see
nothing: at a stiff, heavily loaded contact a Newton step of the soft tissue can turn cells
inside out (J = det F <= 0), where the Ogden energy is not defined and the residual is NaN;
the solve then fails with SNES reason -4 (measured on the whole-hand cylinder in muscles mode,
docs/grasp.md, seventeenth session). Interior-point methods handle the same problem with a
"fraction to the boundary" rule; here the rule is applied to J:

    x_new = x - s y  (PETSc's sign),  s <= 1 largest with  J(s') >= keep * J(0)  for s' <= s

in every cell. det(A - s B) is a cubic in s (A = I + grad u at x, B = grad of the step's
displacement), so the check is a few NumPy operations per cell and grid point; the largest
admissible s is taken on a grid (linear in [1/32, 1], geometric below). A step that keeps
every cell above the bound is left alone, so converging solves are unchanged.
"""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

#: the s grid: 1/32 .. 1 linearly, then 2^-6 .. 2^-24 for steps that invert cells very early
_GRID = np.concatenate([2.0 ** -np.arange(24, 5, -1), np.arange(1, 33) / 32.0])


def _cofactor(M: np.ndarray) -> np.ndarray:
    """Cofactor matrices of a stack (n, 3, 3): rows r1 x r2, r2 x r0, r0 x r1."""
    r0, r1, r2 = M[:, 0], M[:, 1], M[:, 2]
    return np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=1)


def admissible_step(A: np.ndarray, B: np.ndarray, keep: float) -> float:
    """Largest s in (0, 1] on the grid with det(A - s' B) >= keep * det(A) for all grid points
    s' <= s, over the stacks A, B (n, 3, 3) (cells with det A <= 0 are already inverted and
    ignored). 1.0 if no cell comes near the bound; the smallest grid point / 2 if even that
    one violates it."""
    if A.shape[0] == 0:
        return 1.0
    a0 = np.linalg.det(A)
    # det(A + t B) = det A + t <cof A, B> + t^2 <cof B, A> + t^3 det B, with t = -s
    a1 = -np.einsum("nij,nij->n", _cofactor(A), B)
    a2 = np.einsum("nij,nij->n", _cofactor(B), A)
    a3 = -np.linalg.det(B)
    ok_cells = a0 > 0.0
    if not ok_cells.any():
        return 1.0
    a0, a1, a2, a3 = a0[ok_cells], a1[ok_cells], a2[ok_cells], a3[ok_cells]
    s = _GRID[None, :]
    J = a0[:, None] + s * (a1[:, None] + s * (a2[:, None] + s * a3[:, None]))
    bad = (J < keep * a0[:, None]).any(axis=0)  # (grid,)
    if not bad.any():
        return 1.0
    first = int(np.argmax(bad))
    return float(_GRID[first - 1]) if first > 0 else float(_GRID[0]) / 2.0


class InversionGuard:
    """Line-search pre-check (``SNES.setLineSearchPreCheck``) that scales the Newton step ``y``
    so that no cell's J drops below ``keep`` x its value at the current iterate.

    ``w``: the state Function (its space is the SNES vector's layout); ``mixed``: the
    displacement is ``split(w)[0]`` (else ``w`` itself). For P1 displacements grad u is
    constant per cell and J is checked at the centroid; for higher degrees at the vertices and
    the centroid. Owned cells only; the step scale is the minimum over ranks.
    ``shortened`` counts the steps it scaled, ``smallest`` is the smallest scale applied,
    ``min_J`` the smallest cell J at the iterates it scaled a step from and ``min_J_centre``
    that cell's centre (mm, reference configuration; the same on every rank)."""

    def __init__(self, w: fem.Function, *, mixed: bool, keep: float = 0.1):
        if not 0.0 < keep < 1.0:
            raise ValueError(f"keep must be in (0, 1), got {keep}")
        self.keep = float(keep)
        V = w.function_space
        self.comm = V.mesh.comm
        self._wx, self._wy = fem.Function(V), fem.Function(V)
        el = V.ufl_element()
        uel = el.sub_elements()[0] if mixed else el
        if uel.degree() == 1:
            pts = np.array([[0.25, 0.25, 0.25]])
        else:
            pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0],
                            [0.25, 0.25, 0.25]])

        def grad_u(f):
            return ufl.grad(ufl.split(f)[0] if mixed else f)

        self._gx = fem.Expression(grad_u(self._wx), pts)
        self._gy = fem.Expression(grad_u(self._wy), pts)
        mesh = self._mesh = V.mesh
        n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        self.cells = np.arange(n_owned, dtype=np.int32)
        self.shortened = 0
        self.smallest = 1.0
        #: the smallest cell J at an iterate whose step the guard shortened
        self.min_J = float("inf")
        self.min_J_centre: np.ndarray | None = None
        self.last_scale = 1.0  # the scale of the last step checked

    def scale(self, x, y) -> float:
        """The admissible fraction s of the step (x_new = x - s y), same on every rank."""
        for vec, f in ((x, self._wx), (y, self._wy)):
            vec.copy(f.vector)
            f.x.scatter_forward()
        A = self._gx.eval(self.cells).reshape(-1, 3, 3) + np.eye(3)
        B = self._gy.eval(self.cells).reshape(-1, 3, 3)
        with np.errstate(invalid="ignore", over="ignore"):
            s = admissible_step(A, B, self.keep)
        self._A = A  # for min_J, only when the step is shortened
        return self.comm.allreduce(s, op=MPI.MIN)

    def __call__(self, x, y) -> bool:
        s = self.last_scale = self.scale(x, y)
        if s >= 1.0:
            return False
        y.scale(s)
        self.shortened += 1
        self.smallest = min(self.smallest, s)
        self._note_smallest(np.linalg.det(self._A))
        return True

    def reset(self) -> None:
        """Forget the smallest scale and cell J (before a new solve); ``shortened`` counts on."""
        self.smallest, self.min_J, self.min_J_centre = 1.0, float("inf"), None

    def _note_smallest(self, J: np.ndarray) -> None:
        """Keep the smallest cell J over all ranks and its cell's centre (ties, as in congruent
        cells, go to the lexicographically smallest centre: the same on any partition)."""
        from dolfinx.mesh import compute_midpoints

        J_min = self.comm.allreduce(float(J.min(initial=np.inf)), op=MPI.MIN)
        if not J_min < self.min_J:
            return
        tied = self.cells[J == J_min]
        mine = [tuple(c) for c in compute_midpoints(self._mesh, 3, tied)] if len(tied) else []
        centres = [c for part in self.comm.allgather(mine) for c in part]
        self.min_J, self.min_J_centre = J_min, np.array(min(centres))

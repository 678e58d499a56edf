"""Speed of the NumPy Ogden kernel (:mod:`handfe.ogden_p1`) on random deformation gradients:
the stress with its eigendecomposition (``_spectral``, a residual's share) and the tangent from
it (``_tangent``, a Jacobian's extra share). One process; ms, median of ``--repeat``; CSV on
stdout. The grasp at `default` has ~63,000 cells per rank on 2 ranks.

    .venv/bin/python benchmarks/ogden_p1_kernel.py --cells 63000
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from handfe.materials import Ogden
from handfe.ogden_p1 import _spectral, _tangent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=63000, help="number of cells (default 63000)")
    ap.add_argument("--repeat", type=int, default=5, help="repetitions (default 5)")
    a = ap.parse_args()
    if a.cells < 1 or a.repeat < 1:
        ap.error("--cells and --repeat must be >= 1")
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.2 * rng.standard_normal((a.cells, 3, 3))
    skin = Ogden.skin(nu=0.499)
    mu, alpha = np.tile(skin.mu_MPa, (a.cells, 1)), np.tile(skin.alpha, (a.cells, 1))
    sp = _spectral(F, mu, alpha)

    def median_ms(f) -> float:
        ts = []
        for _ in range(a.repeat):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return 1e3 * float(np.median(ts))

    with np.errstate(invalid="ignore", divide="ignore"):
        stress = median_ms(lambda: _spectral(F, mu, alpha))
        tangent = median_ms(lambda: _tangent(F, sp))
    print("cells,stress_ms,tangent_ms")
    print(f"{a.cells},{stress:.1f},{tangent:.1f}")


if __name__ == "__main__":
    main()

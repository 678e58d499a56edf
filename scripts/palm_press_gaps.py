"""Where would the palm press take the object? (rigid, no FE solve)

For a workflow's starting mesh (placement, rigid pre-closing and meshing as `handfe run` does
them; the FE problem is not built), the gap (mm) of each region to the object after the object
moves by 2..12 mm along three candidate directions: the palm's normal at its nearest skin, the
digits' push, and the push kept at the thumb (`handfe.grasp.scene.palm_direction`, the one
`solver.palm_force_N` uses). Negative = the object would be inside that skin. Directions are
printed in the hand frame (x radial, y distal, z palmar). docs/grasp.md, forty-seventh session.

    .venv/bin/python scripts/palm_press_gaps.py workflows/cylindrical.toml coarse
"""
import sys

import numpy as np

import handfe.grasp.scene as scene
from handfe.grasp.outputs import region_of


class _Start(Exception):
    """Raised in place of building the FE problem: carries the starting mesh and object."""

    def __init__(self, model, grasp, obstacle, shift):
        super().__init__()
        self.model, self.grasp, self.obstacle, self.shift = model, grasp, obstacle, shift


def _stop(model, grasp, wf, skin, subcut, obstacle, shift, *args, **kwargs):
    raise _Start(model, grasp, obstacle, shift)


def main(workflow: str, level: str) -> None:
    scene.GraspFE = _stop
    try:
        scene.run_workflow(workflow, mesh=level)
    except _Start as s:
        start = s
    else:
        raise SystemExit("the workflow ran without building its FE problem?")
    surf, ob, sh = start.model.surface, start.obstacle, start.shift
    R = start.model.skeleton.hand_frame.R
    tri_reg = np.array([region_of(c)[0] for c in surf.codes])
    regions = [*start.grasp.digits, "palm"]
    pts = {r: surf.points[np.unique(surf.triangles[tri_reg == r])] for r in regions}
    g, n = ob.gap_normal(pts["palm"], sh)
    palm_n = n[g <= g.min() + 1.0].mean(axis=0)
    dirs = {"the palm's normal": palm_n / np.linalg.norm(palm_n),
            "the digits' push": scene.palm_direction(ob, sh, surf, start.grasp.digits,
                                                     thumb_kept=False)[0],
            "the push kept at the thumb": scene.palm_direction(ob, sh, surf,
                                                               start.grasp.digits)[0]}
    for name, d in dirs.items():
        print(f"{name}: {np.round(R.T @ d, 2)} (hand frame)")
        print("  travel mm  " + "  ".join(f"{r:>7}" for r in regions))
        for t in (2, 4, 6, 8, 10, 12):
            print(f"  {t:9d}  " + "  ".join(
                f"{ob.gap_normal(pts[r], sh + t * d)[0].min():7.2f}" for r in regions))


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2] if len(sys.argv) == 3 else "coarse")

"""The hand-mesh cache (handfe.meshcache, handfe.anatomy.meshing.build_hand): a mesh made once
is read back identically; a cached gmsh failure is reported at once (as a meshing failure, so
a grasp's retry ladder moves on); an unreadable cache file is meshed afresh; HANDFE_MESH_CACHE=0
bypasses the cache. One coarse index-only hand (~10 s of gmsh)."""

from __future__ import annotations

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

from handfe.anatomy import build_hand, load_subject
from handfe.anatomy.meshing import hand_cache_path, parse_digits
from handfe.errors import InputError
from handfe.kinematics import Pose
from handfe.paths import ANATOMY_DIR, SUBJECTS_DIR

POSE = ANATOMY_DIR / "poses" / "precision.toml"


def _tag_measures(model) -> tuple[dict[int, float], dict[int, float]]:
    """Volume per cell tag and area per facet tag (mm^3, mm^2)."""
    msh = model.mesh
    dx = ufl.Measure("dx", domain=msh, subdomain_data=model.cell_tags)
    ds = ufl.Measure("ds", domain=msh, subdomain_data=model.facet_tags)
    one = fem.Constant(msh, 1.0)
    vols = {int(t): fem.assemble_scalar(fem.form(one * dx(int(t))))
            for t in np.unique(model.cell_tags.values)}
    areas = {int(t): fem.assemble_scalar(fem.form(one * ds(int(t))))
             for t in np.unique(model.facet_tags.values)}
    return vols, areas


@pytest.fixture(scope="module")
def subject():
    return load_subject(SUBJECTS_DIR / "S01")


def test_hand_mesh_cache_round_trip(subject, tmp_path, monkeypatch):
    monkeypatch.setenv("HANDFE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HANDFE_MESH_CACHE", raising=False)
    pose = Pose.from_toml(POSE)
    kw = {"digits": "index", "level": "coarse", "comm": MPI.COMM_SELF}
    a = build_hand(subject, pose, **kw)
    path = hand_cache_path(subject, pose, parse_digits("index"), "coarse", True)
    assert path.exists() and path.with_suffix(".npz").exists()
    b = build_hand(subject, pose, **kw)
    assert "from_cache" not in a.quality and b.quality.pop("from_cache") is True
    assert a.quality == b.quality
    for f in ("points", "triangles", "codes"):
        assert np.array_equal(getattr(a.surface, f), getattr(b.surface, f))
    assert b.mesh.topology.index_map(3).size_global == a.mesh.topology.index_map(3).size_global
    assert b.mesh.topology.index_map(0).size_global == a.mesh.topology.index_map(0).size_global
    (va, sa), (vb, sb) = _tag_measures(a), _tag_measures(b)
    assert va.keys() == vb.keys() and sa.keys() == sb.keys()
    for k in va:
        assert vb[k] == pytest.approx(va[k], rel=1e-12)
    for k in sa:
        assert sb[k] == pytest.approx(sa[k], rel=1e-12)

    # an unreadable mesh file: meshed afresh (and cached again; HXT is not deterministic, the
    # cell count varies by a few per mil from run to run)
    path.write_bytes(b"not a mesh")
    c = build_hand(subject, pose, **kw)
    assert "from_cache" not in c.quality
    assert c.quality["cells"] == pytest.approx(a.quality["cells"], rel=0.01)
    assert path.stat().st_size > 1000

    # a cached gmsh failure is raised at once, as a meshing failure
    path.with_suffix(".failed.json").write_text('{"error": "meshing failed for pose P: PLC"}')
    with pytest.raises(InputError, match="meshing failed.*cached failure"):
        build_hand(subject, pose, **kw)

    # the cache off: meshes (and does not read the failure)
    monkeypatch.setenv("HANDFE_MESH_CACHE", "0")
    assert hand_cache_path(subject, pose, parse_digits("index"), "coarse", True) is None
    assert "from_cache" not in build_hand(subject, pose, **kw).quality


def test_cache_key_does_not_depend_on_where_the_checkout_is(subject, tmp_path, monkeypatch):
    """The subject's and the pose's source paths enter the key relative to the checkout: a
    second clone or a worktree reads the meshes the first one cached."""
    import dataclasses

    from handfe.paths import REPO_ROOT

    monkeypatch.setenv("HANDFE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HANDFE_MESH_CACHE", raising=False)
    pose = Pose.from_toml(POSE)
    rel = dataclasses.replace(subject, source=str(subject.source).replace(f"{REPO_ROOT}/", ""))
    rel_pose = Pose(dict(pose.values), source=str(pose.source).replace(f"{REPO_ROOT}/", ""))
    assert str(subject.source).startswith(str(REPO_ROOT)) and rel.source != subject.source
    key = (parse_digits("index"), "coarse", True)
    assert hand_cache_path(subject, pose, *key) == hand_cache_path(rel, rel_pose, *key)
    other = dataclasses.replace(subject, source="elsewhere/S01/anthropometry.toml")
    assert hand_cache_path(other, pose, *key) != hand_cache_path(subject, pose, *key)


def test_a_cached_failure_names_paths_in_the_repo_and_its_cause_reads_short(tmp_path):
    """The failure file is shared by every checkout (the key does not depend on where the
    checkout is): its message names repo paths, and the grasp's retry line shows the cause."""
    import json

    from handfe.anatomy.meshing import _cache_failure, failure_cause
    from handfe.paths import REPO_ROOT

    path = tmp_path / "hand-x.msh"
    _cache_failure(path, f"meshing failed for pose {REPO_ROOT}/subjects/S01/trials.toml grasp "
                         "'precision' opened by 5 deg, pre-closed to contact: gmsh returned an "
                         "empty mesh")
    error = json.loads(path.with_suffix(".failed.json").read_text())["error"]
    assert error.startswith("meshing failed for pose subjects/S01/trials.toml grasp")
    assert failure_cause(error) == "gmsh returned an empty mesh"
    assert failure_cause(error + " (cached failure: /c/hand-x.failed.json; HANDFE_MESH_CACHE=0 "
                         "or deleting the file meshes it again)") \
        == "gmsh returned an empty mesh; cached"
    assert failure_cause("meshing failed for pose P: " + "x" * 200) == "x" * 77 + "..."

"""Grasp workflow inputs and rigid-body mechanics (no FE): configuration errors name file and
key; object placement refuses intersections; ligament law, muscle torques and bone motions."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from handfe.anatomy import load_subject
from handfe.anatomy.meshing import SurfaceData
from handfe.errors import ConfigError, InputError
from handfe.grasp import load_workflow
from handfe.grasp.config import ObjectSpec, parse_overrides
from handfe.grasp.mechanics import (
    DigitArc,
    Kinematics,
    Ligaments,
    closed_pose,
    ligament_force_N,
    muscle_torques,
    opened_pose,
    pre_close,
    released_joints,
)
from handfe.grasp.scene import (
    DigitStepLimiter,
    balance_problems,
    damped_newton_step,
    redo_closing_fraction,
    secant_closing_increment,
)
from handfe.kinematics import Pose
from handfe.paths import REPO_ROOT

SHIPPED = sorted(p.stem for p in (REPO_ROOT / "workflows").glob("*.toml"))


def test_the_three_grasps_ship_their_workflows():
    assert {"cylindrical", "spherical", "precision", "cylindrical_muscles"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_workflows_load(name):
    wf = load_workflow(REPO_ROOT / "workflows" / f"{name}.toml")
    g = wf.grasp_spec()
    assert g.name == name.split("_")[0] and 0.0 < g.friction < 1.0
    assert wf.subject_dir().name == "S01"
    if "_muscles" in name:  # the recipe of the measured muscle-driven runs
        assert wf.loading == "muscles" and wf.solver.muscle_friction_history == "load"
        assert wf.solver.free_object == name.endswith("_free")


def test_the_reduced_muscles_recipe_is_the_coarse_one_with_its_three_keys():
    """workflows/cylindrical_muscles_reduced.toml is cylindrical_muscles.toml (its ``base``)
    with mesh, guard_damping and muscle_stall_rtol changed, nothing else (a key added to it
    that would change the run is caught here)."""
    coarse = load_workflow(REPO_ROOT / "workflows" / "cylindrical_muscles.toml")
    reduced = load_workflow(REPO_ROOT / "workflows" / "cylindrical_muscles_reduced.toml")
    assert (reduced.mesh, coarse.mesh) == ("reduced", "coarse")
    assert reduced.solver.guard_damping and not coarse.solver.guard_damping
    assert reduced.solver.muscle_stall_rtol > coarse.solver.muscle_stall_rtol
    back = dataclasses.replace(reduced, mesh=coarse.mesh, source=coarse.source,
                               solver=dataclasses.replace(
                                   reduced.solver, guard_damping=coarse.solver.guard_damping,
                                   muscle_stall_rtol=coarse.solver.muscle_stall_rtol))
    assert back == coarse


@pytest.mark.parametrize("grasp", ["precision", "spherical"])
def test_the_light_muscles_recipes_are_the_cylinder_one_on_their_grasp_at_a_tenth(grasp):
    """workflows/{precision,spherical}_muscles_light.toml: cylindrical_muscles.toml (their
    ``base``) with grasp and muscle_force_scale = 0.1 changed, nothing else; the muscles-mode
    caveat has nothing to add for them (both ran to the end: docs/grasp.md, thirty-ninth
    session)."""
    from handfe.grasp.scene import muscles_mode_caveat

    base = load_workflow(REPO_ROOT / "workflows" / "cylindrical_muscles.toml")
    light = load_workflow(REPO_ROOT / "workflows" / f"{grasp}_muscles_light.toml")
    assert (light.grasp, light.muscle_force_scale) == (grasp, 0.1)
    assert dataclasses.replace(light, grasp=base.grasp, muscle_force_scale=1.0,
                               source=base.source) == base
    assert muscles_mode_caveat(light.loading, grasp, light.mesh, light.solver,
                               light.muscle_force_scale) == ""


def test_the_full_load_ball_recipe_is_the_cylinder_one_on_the_ball_with_three_keys():
    """workflows/spherical_muscles.toml: cylindrical_muscles.toml (its ``base``) with the
    grasp and the [solver] keys guard_damping, muscle_stall_rtol and inversion_guard changed,
    nothing else (docs/grasp.md, forty-second session)."""
    base = load_workflow(REPO_ROOT / "workflows" / "cylindrical_muscles.toml")
    ball = load_workflow(REPO_ROOT / "workflows" / "spherical_muscles.toml")
    assert (ball.grasp, ball.solver.guard_damping, ball.solver.muscle_stall_rtol,
            ball.solver.inversion_guard) == ("spherical", True, 1e-3, 0.5)
    solver = dataclasses.replace(ball.solver, guard_damping=base.solver.guard_damping,
                                 muscle_stall_rtol=base.solver.muscle_stall_rtol,
                                 inversion_guard=base.solver.inversion_guard)
    assert dataclasses.replace(ball, grasp=base.grasp, solver=solver,
                               source=base.source) == base


def _write(tmp_path: Path, text: str, name: str = "wf.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_a_workflow_takes_its_base_keys_under_its_own(tmp_path):
    """``base``: every key of the base workflow, this file's over it, [solver] key by key; a
    base by name (workflows/) or by a path relative to the file; a subject path of the base
    means the base's folder."""
    (tmp_path / "common" / "subj").mkdir(parents=True)
    (tmp_path / "common" / "subj" / "anthropometry.toml").write_text("")
    _write(tmp_path / "common", 'subject = "subj"\ngrasp = "precision"\nmesh = "coarse"\n'
           '[solver]\ntorque_rtol = 2e-3\nmax_step_deg = 1.0\n', "b.toml")
    (tmp_path / "runs").mkdir()
    p = _write(tmp_path / "runs", 'base = "../common/b.toml"\nmesh = "reduced"\n'
               '[solver]\nmax_step_deg = 2.0\n')
    wf = load_workflow(p)
    assert (wf.mesh, wf.grasp, wf.solver.torque_rtol, wf.solver.max_step_deg) == \
        ("reduced", "precision", 2e-3, 2.0)
    assert wf.subject_dir() == tmp_path / "common" / "subj"
    assert wf.source == str(p)
    shipped = load_workflow("cylindrical_muscles")
    named = load_workflow(_write(tmp_path, 'base = "cylindrical_muscles"\n'))
    assert dataclasses.replace(named, source=shipped.source) == shipped


def test_a_bad_base_is_named_with_its_file(tmp_path):
    """A missing base, a base that is not a string, a loop of bases, and a bad key inside the
    base: each error names the file that has the problem and the key."""
    with pytest.raises(ConfigError, match=r"wf\.toml: 'base' = 'nope\.toml': no workflow file"):
        load_workflow(_write(tmp_path, 'base = "nope.toml"\n'))
    with pytest.raises(ConfigError, match=r"wf\.toml: 'base' = 3"):
        load_workflow(_write(tmp_path, "base = 3\n"))
    _write(tmp_path, 'base = "b.toml"\n', "a.toml")
    _write(tmp_path, 'base = "a.toml"\n', "b.toml")
    with pytest.raises(ConfigError, match=r"'base' = 'a\.toml': the bases form a loop"):
        load_workflow(tmp_path / "a.toml")
    _write(tmp_path, 'grasp = "precision"\n[solver]\ntorque_rtoll = 1e-3\n', "c.toml")
    with pytest.raises(ConfigError, match=r"c\.toml: unknown key 'solver\.torque_rtoll'"):
        load_workflow(_write(tmp_path, 'base = "c.toml"\nmesh = "coarse"\n'))


def test_set_overrides_change_the_named_keys_only():
    """``handfe run --set KEY=VALUE`` (``parse_overrides``): values read as TOML (a bare word as
    a string), [solver] keys one by one over the file's; the rest of the workflow unchanged."""
    over = parse_overrides(["solver.guard_damping=true", "solver.muscle_stall_rtol=3e-4",
                            "mesh=reduced", 'solver.stabilisation_modulus="pressure"',
                            "solver.muscle_final_uzawa=interleaved"])
    assert over == {"mesh": "reduced", "solver": {
        "guard_damping": True, "muscle_stall_rtol": 3e-4, "stabilisation_modulus": "pressure",
        "muscle_final_uzawa": "interleaved"}}
    coarse = load_workflow("cylindrical_muscles")
    wf = load_workflow("cylindrical_muscles", over)
    assert dataclasses.replace(wf, mesh=coarse.mesh, solver=dataclasses.replace(
        wf.solver, guard_damping=False, muscle_stall_rtol=coarse.solver.muscle_stall_rtol,
        stabilisation_modulus=coarse.solver.stabilisation_modulus)) == coarse
    # the shipped reduced recipe is the coarse one with three keys: the same as --set
    reduced = load_workflow("cylindrical_muscles_reduced", None)
    same = load_workflow("cylindrical_muscles", parse_overrides(
        ["mesh=reduced", "solver.guard_damping=true", "solver.muscle_stall_rtol=3e-4"]))
    assert dataclasses.replace(same, source=reduced.source) == reduced


@pytest.mark.parametrize("item, message", [
    ("solver.torque_rtoll=1e-3", r"--set: unknown key 'solver\.torque_rtoll'"),
    ("solver.torque_rtol=-1", r"--set: 'solver\.torque_rtol' = -1.*out of range"),
    ("mesh=coars", r"--set: 'mesh' = 'coars': must be one of"),
    ("solver.guard_damping", r"--set 'solver\.guard_damping': expected KEY=VALUE"),
    ("solver..nu=0.49", r"expected KEY=VALUE"),
    ("mesh.level=coarse", r"--set: 'mesh' = \{'level': 'coarse'\}: expected a string"),
])
def test_bad_set_overrides_are_named(item, message):
    with pytest.raises(ConfigError, match=message):
        parse_overrides([item])


def test_set_overrides_that_clash_with_the_file_name_both():
    with pytest.raises(ConfigError, match=r"precision\.toml with --set: 'solver\.guard_damping'"):
        load_workflow("precision", parse_overrides(["solver.guard_damping=true"]))


def test_handfe_run_set_refuses_a_bad_key_before_running(tmp_path, capsys):
    from handfe.cli import main

    out = tmp_path / "run"
    assert main(["run", "precision", "--set", "solver.max_step_degs=1", "--out",
                 str(out)]) == 2
    assert "--set: unknown key 'solver.max_step_degs'" in capsys.readouterr().err
    assert not out.exists()


def test_handfe_run_refuses_to_drop_the_muscles_settings_in_the_angles_mode(tmp_path, capsys):
    """--loading angles on a light or free-object muscles recipe would run a different grasp
    than its file says (no scale, the object held): refused before anything runs."""
    from handfe.cli import main

    out = tmp_path / "run"
    assert main(["run", "precision_muscles_light", "--loading", "angles", "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert "precision_muscles_light.toml: loading = 'angles' does not use " \
        "muscle_force_scale = 0.1" in err
    assert main(["run", "cylindrical_muscles_free", "--loading", "angles", "--out",
                 str(out)]) == 2
    assert "solver.free_object = true" in capsys.readouterr().err
    assert not out.exists()


def test_show_prints_every_key_as_a_workflow_that_loads_back(tmp_path, capsys):
    """``handfe run FILE --show`` (``workflow_toml``): the keys after base, --set, --mesh and
    --loading, as a TOML that loads to the same workflow; no run, no --out needed."""
    from handfe.cli import main
    from handfe.grasp.config import workflow_toml

    wf = load_workflow("cylindrical_muscles_reduced",
                       parse_overrides(["solver.nu=0.4999", 'solver.friction_smoothing=0.05']))
    back = load_workflow(_write(tmp_path, workflow_toml(wf)))
    assert dataclasses.replace(back, source=wf.source) == wf
    assert main(["run", "cylindrical_muscles_reduced", "--set", "solver.nu=0.4999",
                 "--mesh", "coarse", "--show"]) == 0
    text = capsys.readouterr().out
    assert 'mesh = "coarse"' in text and "guard_damping = true" in text
    assert "nu = 0.4999" in text and "[outputs]" in text
    assert main(["run", "precision"]) == 2  # neither --out nor --show
    assert "--out is required" in capsys.readouterr().err


def test_unknown_key_names_file_and_key(tmp_path):
    p = _write(tmp_path, 'subject = "subjects/S01"\ngrasp = "precision"\nmeshh = "reduced"\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*meshh"):
        load_workflow(p)


def test_bad_values(tmp_path):
    p = _write(tmp_path, 'grasp = "precision"\nloading = "forces"\n')
    with pytest.raises(ConfigError, match="loading"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\ntorque_rtol = -1.0\n')
    with pytest.raises(ConfigError, match="torque_rtol"):
        load_workflow(p)


def test_guard_damping_needs_the_guard(tmp_path):
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nguard_damping = true\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*guard_damping.*inversion_guard"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nguard_damping = true\n'
               'inversion_guard = 0.1\n')
    assert load_workflow(p).solver.guard_damping


def test_muscle_force_scale_is_checked_and_belongs_to_the_muscles_mode(tmp_path):
    """A lighter (or heavier) grip than the EMG estimate: every muscle force x the scale, in
    0.01-2; the angles mode does not use muscle forces, so a scale written there is refused."""
    p = _write(tmp_path, 'grasp = "precision"\nloading = "muscles"\nmuscle_force_scale = 0.1\n')
    assert load_workflow(p).muscle_force_scale == 0.1
    assert load_workflow("cylindrical_muscles").muscle_force_scale == 1.0
    p = _write(tmp_path, 'grasp = "precision"\nloading = "muscles"\nmuscle_force_scale = 0\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'muscle_force_scale' = 0.*out of range"):
        load_workflow(p)
    # refused as written, whatever its value: 1.0 (the default) too
    for text in ("0.5", "1.0"):
        p = _write(tmp_path, f'grasp = "precision"\nmuscle_force_scale = {text}\n')
        with pytest.raises(ConfigError,
                           match=rf"wf\.toml.*'muscle_force_scale' = {text}.*'angles'"):
            load_workflow(p)

    # by --set on a muscle-driven recipe, as a user would lighten it for one run
    wf = load_workflow("cylindrical_muscles", parse_overrides(
        ["muscle_force_scale=0.25"]))
    assert wf.muscle_force_scale == 0.25


def test_a_free_object_belongs_to_the_muscles_mode(tmp_path):
    """The angles mode holds the object (each digit closes to its force against it): a free
    object asked for there is refused, not run held; the muscles mode takes it."""
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nfree_object = true\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'solver\.free_object' = true.*'angles'"):
        load_workflow(p)
    assert not load_workflow(_write(tmp_path, 'grasp = "precision"\n[solver]\n'
                                              'free_object = false\n')).solver.free_object
    assert load_workflow("cylindrical_muscles_free").solver.free_object
    with pytest.raises(ConfigError, match="free_object"):
        load_workflow("cylindrical_muscles_free", parse_overrides(["loading=angles"]))


def test_the_palm_press_belongs_to_the_angles_mode(tmp_path, capsys):
    """solver.palm_force_N presses the object into the palm before the kinematic closing: in
    range, refused in a muscles workflow (written or by --loading muscles) rather than
    dropped."""
    from handfe.cli import main

    p = _write(tmp_path, 'grasp = "cylindrical"\n[solver]\npalm_force_N = 20.0\n')
    assert load_workflow(p).solver.palm_force_N == 20.0
    p = _write(tmp_path, 'grasp = "cylindrical"\n[solver]\npalm_force_N = -1.0\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*palm_force_N.*-1"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "cylindrical"\nloading = "muscles"\n[solver]\n'
               'palm_force_N = 20.0\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'solver\.palm_force_N' = 20.*muscles"):
        load_workflow(p)
    out = tmp_path / "run"
    assert main(["run", "cylindrical", "--set", "solver.palm_force_N=20", "--loading",
                 "muscles", "--out", str(out)]) == 2
    assert "loading = 'muscles' does not use solver.palm_force_N = 20" in \
        capsys.readouterr().err
    assert not out.exists()


def test_contact_scheme_options_validated(tmp_path):
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nnewton_linesearch = "cp"\n')
    with pytest.raises(ConfigError, match="newton_linesearch"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nstick_ratio = 0.0\n')
    with pytest.raises(ConfigError, match="stick_ratio"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\ndigit_force_rtol = 1.5\n')
    with pytest.raises(ConfigError, match="digit_force_rtol"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\ninversion_guard = 1.0\n')
    with pytest.raises(ConfigError, match="inversion_guard"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nresolve_linesearch = "l2"\n')
    with pytest.raises(ConfigError, match="resolve_linesearch"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nuzawa_tangential_relax = 0.0\n')
    with pytest.raises(ConfigError, match="uzawa_tangential_relax"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[outputs]\nloaded_area_kPa = 0.0\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*loaded_area_kPa"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nstabilisation_modulus = "secant"\n')
    with pytest.raises(ConfigError, match="stabilisation_modulus"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\nelement = "p1-p0"\n[solver]\n'
                         'stabilisation_modulus = "tangent"\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*stabilisation_modulus.*p1-p0"):
        load_workflow(p)
    # the default ("tangent", docs/grasp.md twenty-fifth session) does not stop other elements
    assert load_workflow(_write(tmp_path, 'grasp = "precision"\n')).solver \
        .stabilisation_modulus == "tangent"
    assert load_workflow(_write(tmp_path, 'grasp = "precision"\nelement = "p1-p0"\n')) \
        .element == "p1-p0"
    p = _write(tmp_path, 'grasp = "precision"\nelement = "taylor-hood"\n[solver]\n'
                         'stabilisation_modulus = "pressure"\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'pressure'.*taylor-hood"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "precision"\n[solver]\nstabilisation_pressure_factor = 0.0\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*stabilisation_pressure_factor.*0"):
        load_workflow(p)


def test_secant_closing_increment():
    # no history, no force yet, or a falling force: the plain step
    assert secant_closing_increment(None, 0.0, 0.0, 5.0, 0.2, 0.5) == 0.5
    assert secant_closing_increment((0.0, 0.0), 0.5, 0.1, 5.0, 0.2, 0.5) == 0.5
    assert secant_closing_increment((0.0, 1.0), 0.5, 0.9, 5.0, 0.2, 0.5) == 0.5
    # exponential force F = 0.01 exp(4 theta): the secant is exact, aimed at 0.9 x 5 N ...
    f = lambda t: 0.01 * np.exp(4.0 * t)  # noqa: E731
    inc = secant_closing_increment((0.5, f(0.5)), 1.0, f(1.0), 5.0, 0.2, 1.0, max_ratio=1e9)
    assert 0.0 < inc < 1.0 and f(1.0 + inc) == pytest.approx(4.5, rel=1e-12)
    # ... or at 3 x the force now (0.55 N), whichever is smaller (the default ratio)
    inc = secant_closing_increment((0.5, f(0.5)), 1.0, f(1.0), 5.0, 0.2, 1.0)
    assert f(1.0 + inc) == pytest.approx(3.0 * f(1.0), rel=1e-12)
    # (at 2 N, 3x is past the target: the target's secant step)
    inc = secant_closing_increment((0.5, f(0.5)), 1.0, 2.0, 5.0, 0.2, 1.0)
    assert inc == pytest.approx(0.5 * np.log(4.5 / 2.0) / np.log(2.0 / f(0.5)), rel=1e-12)
    # far from the target: capped at the step (without the ratio; with it, the step that
    # triples the force); at the target: the smallest step
    assert secant_closing_increment((0.0, f(0.0)), 0.1, f(0.1), 5.0, 0.2, 0.5,
                                    max_ratio=1e9) == 0.5
    assert secant_closing_increment((0.0, f(0.0)), 0.1, f(0.1), 5.0, 0.2, 0.5) == \
        pytest.approx(np.log(3.0) / 4.0, rel=1e-12)
    assert secant_closing_increment((0.5, f(0.5)), 1.0, 4.6, 5.0, 0.2, 0.5) == \
        pytest.approx(0.01)


def test_redo_closing_fraction():
    aim = 0.975 * 5.0
    # exponential force in the increment's fraction x: the log regula falsi is exact
    f = lambda x: 0.5 * np.exp(3.0 * x)  # noqa: E731
    x = redo_closing_fraction(f(0.0), f(1.0), 5.0, 0.05)
    assert f(x) == pytest.approx(aim, rel=1e-12)
    # a concave log-force (a power law, 0.32 -> 11.5 N): the plain fraction lands high (7.4
    # N); the second try with the start's log-distance halved lands in the 5 % band, where
    # the plain regula falsi again would be above it
    g = lambda x: 8.0 * (0.2 + x) ** 2  # noqa: E731
    x1 = redo_closing_fraction(g(0.0), g(1.0), 5.0, 0.05)
    assert g(x1) > 5.25
    x2 = x1 * redo_closing_fraction(g(0.0), g(x1), 5.0, 0.05, repeat=1)
    plain = x1 * redo_closing_fraction(g(0.0), g(x1), 5.0, 0.05)
    assert 4.75 < g(x2) < 5.25 < g(plain)
    # capped: never the whole increment again, never less than 5 % of it
    assert redo_closing_fraction(1.0, 5.1, 5.0, 0.0) == 0.95
    assert redo_closing_fraction(4.7, 50.0, 5.0, 0.05) == 0.05
    # a start at or above the aim (nothing to interpolate): the smallest fraction
    assert redo_closing_fraction(4.9, 6.0, 5.0, 0.05) == 0.05


def test_torque_step_is_limited_digit_by_digit():
    # the index's large step (a soft direction) is scaled to the cap as a whole (direction
    # kept); the thumb's small step is left alone instead of shrinking with the index's
    lim = DigitStepLimiter(["thumb", "thumb", "index", "index", "index"], 0.1)

    def limit(d):  # how _balance_torques uses it, with Newton's step as the candidate
        lim.update(d)
        return lim.accept(d, d)

    d = np.array([0.01, -0.02, 0.2, -0.4, 0.8])
    out = limit(d)
    assert out[:2] == pytest.approx(d[:2])
    assert out[2:] == pytest.approx(d[2:] / 8.0)
    assert np.abs(out).max() == pytest.approx(0.1)
    # the index overshoots and turns back: its radius halves (twice in a row: a quarter);
    # the thumb, still going the same way, keeps the full radius
    out = limit(np.array([0.5, 0.0, -0.2, 0.4, -0.8]))
    assert out[0] == pytest.approx(0.1) and np.abs(out[2:]).max() == pytest.approx(0.05)
    out = limit(np.array([0.5, 0.0, 0.2, -0.4, 0.8]))
    assert np.abs(out[2:]).max() == pytest.approx(0.025) and out[0] == pytest.approx(0.1)
    # capped and going on the same way: the radius grows back (never above the start)
    assert np.abs(limit(np.array([0.5, 0.0, 0.2, -0.4, 0.8]))[2:]).max() == pytest.approx(0.05)
    for _ in range(4):
        out = limit(np.array([0.5, 0.0, 0.2, -0.4, 0.8]))
    assert np.abs(out[2:]).max() == pytest.approx(0.1)
    # an uncapped Newton step (0.02) that overshoots: the next one is at most half of it
    limit(np.array([0.0, 0.0, 0.0, 0.0, 0.02]))
    out = limit(np.array([0.0, 0.0, 0.0, 0.0, -0.05]))
    assert out[4] == pytest.approx(-0.01)


def test_damped_newton_step_keeps_the_stiff_direction():
    # a digit with a stiff (1000 N mm/rad) and a soft (1 N mm/rad) direction: Newton's step
    # is 0.1 rad along the stiff one, 10 rad along the soft; within a 0.5 rad radius the damped
    # step reaches the radius and keeps > 95 % of the stiff part (Newton's scaled: ~5 %)
    R = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    K = R @ np.diag([1000.0, 1.0]) @ R.T
    g = R @ np.array([100.0, 10.0])
    K4, g4 = np.zeros((4, 4)), np.zeros(4)
    K4[:2, :2], g4[:2] = K, g
    K4[2:, 2:], g4[2:] = np.eye(2) * 50.0, [1.0, -2.0]   # a second digit, inside its radius
    d = damped_newton_step(K4, g4, ["index", "index", "thumb", "thumb"],
                           {"index": 0.5, "thumb": 0.5})
    stiff, soft = R.T @ d[:2]
    assert np.abs(d[:2]).max() == pytest.approx(0.5, rel=1e-6)
    assert 0.095 < stiff < 0.1 and 0.0 < soft < 10.0
    newton = R @ [0.1, 10.0]
    assert (R.T @ (newton * 0.5 / np.abs(newton).max()))[0] < 0.006
    assert d[2:] == pytest.approx([0.02, -0.04])   # undamped: Newton's


def test_missing_subject_and_grasp(tmp_path):
    p = _write(tmp_path, 'subject = "subjects/S99"\ngrasp = "precision"\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'subject'.*S99"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "lateral"\n')
    with pytest.raises(ConfigError, match=r"'grasp' = 'lateral'.*precision"):
        load_workflow(p)


def test_bad_grasp_file(tmp_path):
    g = _write(tmp_path, 'digits = ["index", "sixth"]\n', "g.toml")
    p = _write(tmp_path, f'grasp = "{g}"\n')
    with pytest.raises(ConfigError, match="sixth"):
        load_workflow(p)
    g = _write(tmp_path, '[object]\nshape = "cone"\n', "g.toml")
    with pytest.raises(ConfigError, match=r"g\.toml.*object\.shape.*cone"):
        load_workflow(p)


def _ball_surface(radius: float, code: int) -> SurfaceData:
    """A triangulated sphere of skin (one region code) centred at the origin."""
    import scipy.spatial

    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 3))
    x /= np.linalg.norm(x, axis=1)[:, None]
    hull = scipy.spatial.ConvexHull(x)
    return SurfaceData(radius * x, hull.simplices, np.full(len(hull.simplices), code))


def test_placement_refuses_intersection_and_finds_snug_position():
    from handfe.anatomy.skeleton import Frame
    from handfe.grasp.scene import make_obstacle, place_object

    H = Frame(np.eye(3), np.zeros(3))
    surf = _ball_surface(30.0, 160)  # "palm" skin: a hollow ball of radius 30 mm
    spec = ObjectSpec(shape="sphere", radius_mm=10.0, centre_mm=(5.0, 0.0, 0.0),
                      search_mm=(15.0, 15.0, 15.0), min_clearance_mm=0.2)
    ob = make_obstacle(spec, H)
    shift, clearance, gaps = place_object(ob, spec, H, surf, ("palm",), "g.toml")
    # inside a hollow ball the snug position touches it (gap -> min clearance)
    assert clearance == pytest.approx(0.2, abs=0.05)
    big = ObjectSpec(shape="sphere", radius_mm=40.0, centre_mm=(0.0, 0.0, 0.0),
                     search_mm=(5.0, 5.0, 5.0))
    with pytest.raises(ConfigError, match=r"g\.toml.*'object' intersects"):
        place_object(make_obstacle(big, H), big, H, surf, ("palm",), "g.toml")


def test_ligament_law_continuous_and_slack():
    L0, k, et = 10.0, 40.0, 0.06
    assert ligament_force_N(9.0, L0, k, et) == 0.0
    e = L0 * (1 + et)
    assert ligament_force_N(e - 1e-9, L0, k, et) == pytest.approx(
        ligament_force_N(e + 1e-9, L0, k, et), rel=1e-6)
    assert ligament_force_N(e + 1.0, L0, k, et) - ligament_force_N(e, L0, k, et) == \
        pytest.approx(k)


def test_muscle_torques_sum_shares_and_arms():
    joints = released_joints(("index",))
    tq = muscle_torques({"FDP": 100.0, "FDS": 0.0}, joints)
    # FDP share 1/4 per finger, moment arms 11.0 / 7.5 / 4.5 mm (anatomy/moment_arms.csv)
    np.testing.assert_allclose(tq, [25 * 11.0, 25 * 7.5, 25 * 4.5])


def test_tendon_splits_share_each_muscle_whole_and_scale_the_torques():
    """Every workflow tendon_split gives each muscle's tendons shares summing to 1; the
    holzbaur2005 split is the compartments' peak forces over their sum (anatomy/tendon_splits.csv:
    little FDS 75.3 / 667.8 N, FDP 236.8 / 819.4 N), so the little finger's FDS torque falls
    by that share over 1/4 and its FDP torque rises likewise; the thumb's muscles keep theirs."""
    from handfe.anatomy.tables import TENDON_SPLITS, tendon_shares

    for split in TENDON_SPLITS:
        shares = tendon_shares(split)
        for m in {m for m, _d in shares}:
            assert sum(v for (mm, _d), v in shares.items() if mm == m) == pytest.approx(1.0)
    holz = tendon_shares("holzbaur2005")
    assert holz["FDS", "little"] == pytest.approx(75.3 / 667.8)
    assert holz["FDP", "middle"] == pytest.approx(212.4 / 819.4)
    joints = released_joints(("thumb", "little"))
    for m, ratio in (("FDS", 75.3 / 667.8 / 0.25), ("FDP", 236.8 / 819.4 / 0.25),
                     ("AP", 1.0)):
        eq = muscle_torques({m: 100.0}, joints)
        np.testing.assert_allclose(muscle_torques({m: 100.0}, joints, "holzbaur2005"),
                                   eq * ratio, rtol=1e-12)
        assert np.abs(eq).max() > 0.0


def test_a_tendon_split_is_checked(tmp_path):
    """An unknown split is refused naming the file, the key and the value; a split belongs to
    the muscles mode; a split table that leaves out a digit a muscle inserts on is refused;
    the table is read once per split, each caller getting a dict of its own."""
    from handfe.anatomy.tables import _tendon_shares, tendon_shares

    p = _write(tmp_path, 'grasp = "spherical"\nloading = "muscles"\ntendon_split = "brand"\n')
    with pytest.raises(ConfigError, match=r"wf\.toml.*'tendon_split' = 'brand'"):
        load_workflow(p)
    p = _write(tmp_path, 'grasp = "spherical"\ntendon_split = "holzbaur2005"\n')
    with pytest.raises(ConfigError, match=r"'tendon_split' = 'holzbaur2005'.*loading = 'angles'"):
        load_workflow(p)
    # the key as written, whatever its value: the angles mode has no muscle loads to split
    p = _write(tmp_path, 'grasp = "spherical"\ntendon_split = "equal"\n')
    with pytest.raises(ConfigError, match=r"'tendon_split' = 'equal'.*loading = 'angles'"):
        load_workflow(p)
    assert load_workflow("spherical_muscles", parse_overrides(
        ["tendon_split=holzbaur2005"])).tendon_split == "holzbaur2005"
    d = tmp_path / "anatomy"
    d.mkdir()
    (d / "insertions.csv").write_text((REPO_ROOT / "anatomy" / "insertions.csv").read_text())
    (d / "tendon_splits.csv").write_text("split,muscle,digit,weight,source\n"
                                         "x,FDS,index,1,t\nx,FDS,middle,1,t\n")
    with pytest.raises(InputError, match=r"tendon_splits\.csv: split 'x' gives FDS .*little"):
        tendon_shares("x", str(d))
    with pytest.raises(InputError, match=r"no tendon split 'y' \(known: equal, x\)"):
        tendon_shares("y", str(d))
    a = tendon_shares("holzbaur2005")
    hits = _tendon_shares.cache_info().hits
    a["FDS", "little"] = 0.0
    assert tendon_shares("holzbaur2005")["FDS", "little"] == pytest.approx(75.3 / 667.8)
    assert _tendon_shares.cache_info().hits == hits + 1  # not read again


def test_bone_motions_identity_and_rotation():
    subj = load_subject(REPO_ROOT / "subjects" / "S01")
    pose = Pose.from_toml(REPO_ROOT / "anatomy" / "poses" / "precision.toml")
    joints = released_joints(("thumb", "index", "middle"))
    kin = Kinematics(subj, pose, joints)
    mot = kin.motions(kin.skeleton(kin.theta0))
    for R, t in mot.values():
        np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(t, 0.0, atol=1e-9)
    th = kin.theta0.copy()
    i = [j.name for j in joints].index("index_pip")
    th[i] += 10.0
    mot = kin.motions(kin.skeleton(th))
    R, _ = mot["index_mp"]
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(mot["index_pp"][0], np.eye(3), atol=1e-12)
    lig = Ligaments(kin.skel0, set(kin.frames0))
    assert len(lig.rows) > 20


def test_opened_pose_clamps_to_limits():
    pose = Pose({"index_dip_flexion": 3.0, "index_pip_flexion": 40.0})
    op = opened_pose(pose, ("index",), 10.0)
    assert op["index_pip_flexion"] == pytest.approx(30.0)
    assert op["index_dip_flexion"] >= -30.0  # clamped at the table's lower limit


def test_pre_close_stops_at_the_clearance_and_flags_a_miss():
    """Rigid pre-closing: the index pad (points around the distal bone) closes onto a ball
    in front of it until the gap is the clearance (bisection to 0.01 deg); a ball off the
    flexion arc is reported as missed; the closed pose adds the angle to every released joint."""
    from handfe.contact import Sphere

    subj = load_subject(REPO_ROOT / "subjects" / "S01")
    pose = Pose.from_toml(REPO_ROOT / "anatomy" / "poses" / "precision.toml")
    kin = Kinematics(subj, pose, released_joints(("index",)))
    frame = kin.skel0.bones["index_dp"].frame
    rng = np.random.default_rng(0)
    local = rng.normal(size=(200, 3))
    local = 6.0 * local / np.linalg.norm(local, axis=1, keepdims=True)
    pts = frame.o + local @ frame.R.T
    arc = DigitArc(subj, pose, ("index",), pts, [("index", "distal")] * len(pts))
    # a ball on the path of the pad: where the pad is after 10 deg more flexion, 8 mm ahead
    ahead = arc.moved("index", 10.0).mean(axis=0)
    ball = Sphere(centre=tuple(ahead + 3.0 * (ahead - pts.mean(axis=0)) / np.linalg.norm(
        ahead - pts.mean(axis=0))), radius=5.0)

    def gap(x):
        return ball.gap_normal(x)[0]

    c = pre_close(arc, gap, clearance_mm=0.5)["index"]
    assert c.reaches and 0.0 < c.closing_deg < 20.0
    assert c.gap_after_mm == pytest.approx(0.5, abs=0.05)
    assert gap(arc.moved("index", c.closing_deg - 0.5)).min() > 0.5
    far = Sphere(centre=tuple(pts.mean(axis=0) + 80.0 * frame.R[:, 0]), radius=5.0)
    miss = pre_close(arc, lambda x: far.gap_normal(x)[0], clearance_mm=0.5)["index"]
    assert not miss.reaches
    closed = closed_pose(pose, {"index": c})
    for j in released_joints(("index",)):
        assert closed[j.dof] == pytest.approx(min(pose[j.dof] + c.closing_deg, kin.hi[
            [k.dof for k in kin.joints].index(j.dof)]))


class _FakeClosing:
    """Stand-in for :class:`handfe.grasp.scene.GraspFE` in the angles-mode closing loop: each
    digit's force grows exponentially with its closing angle; a step that moves the thumb
    together with another digit 'fails to converge' (as the whole-hand cylinder did)."""

    def __init__(self, digits):
        from types import SimpleNamespace

        from handfe.grasp.config import SolverSpec

        self.grasp = SimpleNamespace(digits=digits)
        self.joints = [SimpleNamespace(digit=d) for d in digits]
        self.kin = SimpleNamespace(hi=np.full(len(digits), 90.0),
                                   clamp=lambda t: np.minimum(t, 90.0))
        self.wf = SimpleNamespace(solver=SolverSpec(closing_secant=True, step_uzawa=False,
                                                    digit_force_N=5.0, digit_force_rtol=0.2,
                                                    closing_deg=12.0, closing_step_deg=0.5))
        self.theta = np.zeros(len(digits))
        self.stalled = {}
        self.log = []
        self.steps = []

    def say(self, msg):
        self.log.append(msg)

    def digit_forces(self):
        return {d: 0.05 * float(np.expm1(1.2 * t))
                for d, t in zip(self.grasp.digits, self.theta, strict=True)}

    def _go_to(self, theta, *, label, max_cuts=6):
        from handfe.errors import SolverError

        moving = [d for d, a, b in zip(self.grasp.digits, theta, self.theta, strict=True)
                  if a != b]
        if "thumb" in moving and len(moving) > 1:
            raise SolverError(f"load step '{label}' did not converge", load_step=1)
        self.steps.append({"step": label, "moving": moving})  # as GraspFE records steps
        self.theta = np.array(theta, dtype=float)

    def _snapshot(self):
        return {"theta": self.theta.copy()}

    def _restore(self, snap):
        self.theta = snap["theta"].copy()

    def _closing_increment(self, last, closed, force):
        from handfe.grasp.scene import GraspFE

        return GraspFE._closing_increment(self, last, closed, force)

    def _overshoots(self, active, before):
        from handfe.grasp.scene import GraspFE

        return GraspFE._overshoots(self, active, before)

    def _loose(self):  # Newton tolerances: nothing to loosen in a stand-in
        import contextlib

        return contextlib.nullcontext()

    def _tighten(self, *, stalled=False):
        pass

    def _close_digits(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE._close_digits(self)

    def _stiffen(self):
        pass

    def _scale_loose(self, forces):
        pass

    def augment(self, tol_mm=None, *, creep=True, stop=None):
        pass

    def _final_phase(self):
        pass

    def torques(self):
        return {}


def test_closing_redoes_a_failed_multi_digit_step_one_digit_at_a_time():
    from handfe.grasp.scene import GraspFE

    fake = _FakeClosing(("thumb", "index", "middle"))
    GraspFE.solve_angles(fake)
    assert fake.stalled == {}
    assert any("one digit at a time" in m for m in fake.log)
    # after the failure: one digit per step
    assert all(len(st["moving"]) == 1 for st in fake.steps[1:])
    for d, f in fake.digit_forces().items():
        assert 4.0 <= f <= 6.0, (d, f)
    # the closing history (summary.json steps): the digit forces after each closing step
    assert fake.steps[-1]["digit_force_N"] == fake.digit_forces()
    assert all("digit_force_N" in st for st in fake.steps)


class _FakePalm:
    """Stand-in for :class:`handfe.grasp.scene.GraspFE` in the palm's press: the palm's force
    grows exponentially with the object's travel past the palm's starting gap (a soft pad
    that stiffens), along the palm direction only; optionally one step 'fails to converge'."""

    def __init__(self, gap_mm=2.0, fail_beyond_mm=None, wall_N_per_mm2=0.0, **solver):
        from types import SimpleNamespace

        from handfe.grasp.config import SolverSpec

        self.wf = SimpleNamespace(solver=SolverSpec(
            closing_secant=True, step_uzawa=False, digit_force_rtol=0.2,
            **{"palm_force_N": 20.0, "palm_step_mm": 0.5, "palm_travel_mm": 15.0, **solver}))
        self.palm_direction = np.array([0.0, 0.6, -0.8])
        self.palm_gap_mm = gap_mm
        self.contact = SimpleNamespace(translation=SimpleNamespace(value=np.array([1., 2., 3.])))
        self.t0 = self.contact.translation.value.copy()
        self.theta = np.zeros(2)
        self.fail_beyond_mm = fail_beyond_mm
        self.wall = wall_N_per_mm2  # a stiff layer 1 mm into the pad: + wall x (depth - 1)^2
        self.steps, self.log, self.moves = [], [], []

    def travel(self):
        return float((self.contact.translation.value - self.t0) @ self.palm_direction)

    def palm_force(self):
        depth = max(0.0, self.travel() - self.palm_gap_mm)
        f = 0.2 * float(np.expm1(0.9 * depth)) + self.wall * max(0.0, depth - 1.0) ** 2
        return -f * self.palm_direction

    def say(self, msg):
        self.log.append(msg)

    def _go_to(self, theta, *, label, max_cuts=6, translation=None):
        from handfe.errors import SolverError

        t = np.asarray(translation, dtype=float)
        off = (t - self.t0) - ((t - self.t0) @ self.palm_direction) * self.palm_direction
        assert np.allclose(off, 0.0) and np.array_equal(theta, self.theta)
        if self.fail_beyond_mm is not None and (t - self.t0) @ self.palm_direction \
                > self.fail_beyond_mm:
            raise SolverError(f"load step '{label}' did not converge after 6 cuts",
                              load_step=len(self.steps) + 1)
        self.moves.append(float((t - self.t0) @ self.palm_direction))
        self.contact.translation.value = t
        self.steps.append({"step": label})

    def _snapshot(self):
        return {"t": self.contact.translation.value.copy()}

    def _restore(self, snap):
        self.contact.translation.value = snap["t"].copy()

    def _scale_loose(self, forces):
        pass

    def _stiffen(self):
        pass


def test_the_palm_press_direction_is_the_digits_push_kept_at_the_thumb():
    """palm_direction: -sum of the object's normals at each digit's nearest skin point, less
    the part that would move the object away from the thumb; the palm's gap; |sum n|."""
    from handfe.contact import Sphere
    from handfe.grasp.outputs import REGIONS, SKIN_OUTER_GMSH
    from handfe.grasp.scene import palm_direction

    where = {"thumb": (12.0, 0.0, 0.0), "index": (0.0, 12.0, 0.0), "middle": (0.0, 0.0, 12.0),
             "palm": (0.0, 0.0, -15.0)}
    pts, tris, codes = [], [], []
    for r, c in where.items():
        k = len(pts)
        pts += [np.add(c, e) for e in ((0, 0, 0), (0.1, 0.1, 0), (0, 0.1, 0.1))]
        tris.append([k, k + 1, k + 2])
        codes.append(SKIN_OUTER_GMSH + 10 * (REGIONS.index(r) + 1) + 1)
    surf = SurfaceData(np.array(pts), np.array(tris), np.array(codes))
    ball = Sphere(centre=(0.0, 0.0, 0.0), radius=10.0)
    d, gap, size = palm_direction(ball, np.zeros(3), surf, ("thumb", "index", "middle"),
                                  thumb_kept=False)
    assert d == pytest.approx(-np.ones(3) / np.sqrt(3.0), abs=0.01)
    assert size == pytest.approx(np.sqrt(3.0), abs=0.02) and gap == pytest.approx(4.9, abs=0.01)
    d, _, _ = palm_direction(ball, np.zeros(3), surf, ("thumb", "index", "middle"))
    assert d == pytest.approx([0.0, -1.0 / np.sqrt(2.0), -1.0 / np.sqrt(2.0)], abs=0.01)
    with pytest.raises(InputError, match="no palm skin"):
        palm_direction(ball, np.zeros(3), SurfaceData(np.array(pts[:9]), np.array(tris[:3]),
                                                      np.array(codes[:3])), ("index",))


def test_the_palm_press_moves_the_object_to_the_palms_force():
    from handfe.grasp.scene import GraspFE

    fake = _FakePalm(gap_mm=2.0)
    GraspFE._press_palm(fake)
    f = float(np.linalg.norm(fake.palm_force()))
    assert 16.0 <= f <= 24.0  # within digit_force_rtol of palm_force_N
    # the first move crosses the starting gap at once, by half a step past it
    assert fake.moves[0] == pytest.approx(2.25)
    assert fake.palm_press["travel_mm"] == pytest.approx(fake.travel())
    assert fake.palm_press["force_N"] == pytest.approx(f)
    assert fake.palm_press["direction"] == pytest.approx([0.0, 0.6, -0.8])
    assert "stalled" not in fake.palm_press
    # every move tried past the first is a secant step of at most palm_step_mm
    tried = np.diff([0.0] + fake.moves)
    assert np.all(np.abs(tried[1:]) <= 0.5 + 1e-12)
    assert fake.steps[-1]["palm_force_N"] == pytest.approx(f)
    # a pad that stiffens abruptly: the step past the band is redone smaller, into it
    stiff = _FakePalm(gap_mm=2.0, wall_N_per_mm2=1000.0)
    GraspFE._press_palm(stiff)
    assert any("overshoots 20 N: step redone smaller" in m for m in stiff.log)
    assert 16.0 <= np.linalg.norm(stiff.palm_force()) <= 24.0


def test_the_palm_press_stops_where_a_step_fails_and_at_its_travel():
    from handfe.grasp.scene import GraspFE

    fake = _FakePalm(gap_mm=2.0, fail_beyond_mm=4.0)
    GraspFE._press_palm(fake)
    assert "did not converge" in fake.palm_press["stalled"]
    assert fake.travel() <= 4.0 and fake.palm_press["travel_mm"] == pytest.approx(fake.travel())
    assert any("press stops here" in m for m in fake.log)
    short = _FakePalm(gap_mm=2.0, palm_travel_mm=3.0)
    GraspFE._press_palm(short)
    assert short.travel() == pytest.approx(3.0)
    assert np.linalg.norm(short.palm_force()) < 16.0 and "stalled" not in short.palm_press


class _FakeUzawa:
    """Stand-in for :class:`handfe.grasp.scene.GraspFE` in the Uzawa phase: one multiplier whose
    exact value is 10; an Uzawa update jumps to it, but Newton 'fails' on a change of the
    multiplier larger than 3 from the last converged state (as the pinch's re-solves did)."""

    def __init__(self):
        from types import SimpleNamespace

        from handfe.grasp.config import SolverSpec

        arr = SimpleNamespace(array=np.zeros(1))
        self.contact = SimpleNamespace(
            lambda_n=SimpleNamespace(x=arr), lambda_t=None, u_ref=None,
            k_n=SimpleNamespace(value=1.0), history_due=False, apply_history=lambda: None,
            adaptive_penalty=None, last_penetration_mm=0.0, last_creep_mm=0.0,
            penetration_tol_mm=0.01, stick_tol_mm=0.02, augment=self._augment,
            set_penalty=lambda k: setattr(self.contact.k_n, "value", k))
        self.wf = SimpleNamespace(solver=SolverSpec(max_augment=12))
        self.augmentations = 0
        self.converged = 0.0
        self.max_change = 3.0  # largest multiplier change Newton 'follows'
        self.resolves: list[tuple[float, bool]] = []
        self.tangential: list[bool] = []  # each update's tangential argument

    def _augment(self, final, *, tangential=True):
        lam = self.contact.lambda_n.x.array
        pen = abs(10.0 - lam[0]) / 100.0  # mm
        self.contact.last_penetration_mm = pen
        if pen <= self.contact.penetration_tol_mm:
            return True, pen
        self.tangential.append(tangential)
        lam[0] = 10.0
        return False, pen

    def _resolve(self, what, undo):
        lam = float(self.contact.lambda_n.x.array[0])
        ok = abs(lam - self.converged) <= self.max_change
        self.resolves.append((lam - self.converged, ok))
        if ok:
            self.converged = lam
        else:
            undo()
        return ok

    def _relax_multipliers(self, relax, start, new, *, normal=True):
        from handfe.grasp.scene import GraspFE

        return GraspFE._relax_multipliers(self, relax, start, new, normal=normal)

    def _contact_data(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE._contact_data(self)

    def _set_contact_data(self, data):
        from handfe.grasp.scene import GraspFE

        GraspFE._set_contact_data(self, data)


def test_uzawa_phase_keeps_the_under_relaxation_a_failed_update_needed():
    from handfe.grasp.scene import GraspFE

    fake = _FakeUzawa()
    GraspFE.augment(fake)
    # the first update fails at x1 and x0.5 and converges at x0.25; every later update starts
    # at x0.25 instead of failing twice again
    assert [ok for _, ok in fake.resolves[:3]] == [False, False, True]
    assert all(ok for _, ok in fake.resolves[3:])
    assert fake.contact.last_penetration_mm <= 0.01
    assert abs(fake.converged - 10.0) <= 1.0


def test_uzawa_phase_stops_when_the_kept_under_relaxation_fails():
    """Without a depth cap the halving stops at 0.3: an update that fails at the kept x0.25
    ends the phase instead of halving on."""
    from handfe.grasp.scene import GraspFE

    fake = _FakeUzawa()
    resolve = fake._resolve

    def stricter_after_first(what, undo):
        ok = resolve(what, undo)
        if ok:
            fake.max_change = 1.0  # the next update at x0.25 (a change of 1.875) fails
        return ok

    fake._resolve = stricter_after_first
    GraspFE.augment(fake)
    assert [ok for _, ok in fake.resolves] == [False, False, True, False]


def test_uzawa_depth_cap_under_relaxes_deep_updates_only():
    """``max_depth_mm`` (solver.muscle_uzawa_max_mm): an update at 0.1 mm takes 0.03/0.1 of its
    multiplier change, so Newton follows it without a failed try (without the cap: two)."""
    from handfe.grasp.scene import GraspFE

    fake = _FakeUzawa()
    GraspFE.augment(fake, max_depth_mm=0.03)
    # penetrations 0.1, 0.07, 0.04 mm: 0.3, 0.43, 0.75 of the changes 10, 7, 4
    assert [d for d, _ in fake.resolves] == pytest.approx([3.0, 3.0, 3.0])
    assert all(ok for _, ok in fake.resolves)
    assert fake.contact.last_penetration_mm <= 0.01
    # a cap above the penetration changes nothing: the full update first (which fails here)
    fake = _FakeUzawa()
    GraspFE.augment(fake, max_depth_mm=0.5)
    assert fake.resolves[0] == (pytest.approx(10.0), False)


class _FakeNode(_FakeUzawa):
    """One contact node in the Uzawa phase with the pressure-following penalty: an update is
    lambda += k pen (MPa), and each re-solve sets the node's penetration (mm) by
    ``response(lambda, k)``; Newton always converges."""

    def __init__(self, response, k0: float):
        super().__init__()
        self.response = response
        self.pen = response(0.0, k0)  # the state solved with lambda = 0
        c = self.contact
        c.adaptive_penalty = 10.0
        c.k_n.value = k0
        c.augment = self._node_augment
        self.wf.solver = type(self.wf.solver)(max_augment=14)
        self.penalties: list[float] = []

    def _node_augment(self, final, *, tangential=True):
        c = self.contact
        c.last_penetration_mm = self.pen
        if self.pen <= c.penetration_tol_mm:
            return True, self.pen
        c.lambda_n.x.array[0] += c.k_n.value * self.pen
        return False, self.pen

    def _resolve(self, what, undo):
        self.penalties.append(float(self.contact.k_n.value))
        self.pen = self.response(float(self.contact.lambda_n.x.array[0]),
                                 float(self.contact.k_n.value))
        return True


def test_uzawa_penalty_doubling_stops_when_it_does_not_help():
    """A vertex at the rim of a patch, 0.023 mm into the object while its facets' Gauss points
    sit 0.08 mm off it (the matched-force cylinder's second step, docs/grasp.md, thirty-fifth
    session): the Gauss points push only once 0.67 lambda > k x 0.08, so a doubling per update
    keeps lambda / k bounded and the node never moves. One doubling that does not speed up the
    fall ends the doubling; lambda then grows at a fixed k and the node comes out."""
    from handfe.grasp.scene import GraspFE

    def rim(lam, k, pen0=0.023, w=0.67, g_gauss=0.08, compliance_mm_per_MPa=100.0):
        return max(0.0, pen0 - compliance_mm_per_MPa * max(0.0, w * lam - k * g_gauss))

    fake = _FakeNode(rim, 0.0064)
    GraspFE.augment(fake)
    assert fake.contact.last_penetration_mm <= 0.01
    assert max(fake.penalties) == pytest.approx(2 * 0.0064)  # one doubling, then none
    # the former rule (double whenever the penetration falls by < 2x) stalls at 0.023 mm
    k, lam, pen = 0.0064, 0.0, 0.023
    for _ in range(14):
        lam += k * pen
        k *= 2.0
        pen = rim(lam, k)
    assert pen == pytest.approx(0.023)


def test_uzawa_penalty_doubles_while_it_speeds_up_the_fall():
    """A stiffened pad (tissue stiffness K = 40 x the penalty, linear): each update removes
    k / (K + k) of the penetration, so every doubling speeds up the fall and is kept."""
    from handfe.grasp.scene import GraspFE

    K = 40 * 0.0064

    def pad(lam, k, pen0=0.1):
        return max(0.0, (K * pen0 - lam) / (K + k))

    fake = _FakeNode(pad, 0.0064)
    GraspFE.augment(fake)
    assert fake.contact.last_penetration_mm <= 0.01
    assert fake.penalties[-1] >= 8 * 0.0064


def _with_stick_history(fake, anchors: bool = False):
    """The fake with stick multipliers and a due return mapping that changes them (+1; as
    RigidContact.on_step does after an accepted step, before any re-solve); with ``anchors``
    also stick anchors, which the mapping moves by +2 (those of slipping nodes)."""
    from types import SimpleNamespace

    c = fake.contact
    c.lambda_t = SimpleNamespace(x=SimpleNamespace(array=np.zeros(3)))
    if anchors:
        c.u_ref = SimpleNamespace(x=SimpleNamespace(array=np.zeros(3)))

    def apply_history():
        if c.history_due:
            c.lambda_t.x.array[:] += 1.0
            if anchors:
                c.u_ref.x.array[:] += 2.0
            c.history_due = False

    c.apply_history = apply_history
    c.history_due = True
    return fake


def test_failed_uzawa_update_leaves_the_state_with_the_data_it_balances():
    # the reduced spherical grasp (2 Dec 2026): the last closing step converged, its friction
    # return mapping changed the stick multipliers, the final Uzawa update failed at x1, x0.5
    # and x0.25 - and the run reported the converged state with the changed multipliers, an
    # equilibrium error of 0.18. Now the phase ends on the data the state was solved with
    from handfe.grasp.scene import GraspFE

    fake = _with_stick_history(_FakeUzawa())
    fake.max_change = 0.0  # Newton follows no update
    GraspFE.augment(fake)
    assert [ok for _, ok in fake.resolves] == [False, False, False]
    assert fake.contact.lambda_n.x.array[0] == 0.0
    assert np.all(fake.contact.lambda_t.x.array == 0.0)  # the return mapping is still due
    assert fake.contact.history_due
    assert fake.contact.k_n.value == 1.0


def test_uzawa_phase_with_nothing_to_do_leaves_the_return_mapping_due():
    from handfe.grasp.scene import GraspFE

    fake = _with_stick_history(_FakeUzawa())
    fake.contact.lambda_n.x.array[0] = 10.0  # already exact: no update
    GraspFE.augment(fake)
    assert fake.resolves == []
    assert np.all(fake.contact.lambda_t.x.array == 0.0) and fake.contact.history_due


def test_converged_uzawa_update_applies_the_return_mapping_first():

    from handfe.grasp.scene import GraspFE

    fake = _with_stick_history(_FakeUzawa(), anchors=True)
    c = fake.contact
    GraspFE.augment(fake)
    assert fake.resolves[-1][1] and not fake.contact.history_due
    # the first update converged at x0.25 (above): of the mapping's change too, not of the
    # Uzawa change alone with the mapping at full strength
    assert [ok for _, ok in fake.resolves[:3]] == [False, False, True]
    assert np.all(fake.contact.lambda_t.x.array == 0.25)  # applied once, not undone
    assert np.all(c.u_ref.x.array == 0.5)  # the anchors by the same share
    fake = _with_stick_history(_FakeUzawa())
    fake.max_change = 20.0  # a full update converges: the full mapping with it
    GraspFE.augment(fake)
    assert np.all(fake.contact.lambda_t.x.array == 1.0)
    assert fake.tangential == [True]  # uzawa_tangential_relax = 1: lambda_t <- t_T on top


def test_uzawa_tangential_relax_takes_a_share_of_the_mapping_and_the_full_normal_update():
    """``solver.uzawa_tangential_relax`` < 1: the due return mapping is the update's tangential
    step (no second lambda_t <- t_T), and the stick data take that share of its change while
    the normal multiplier takes the whole update (the reduced cylinder's first re-solve after
    each closing step: 11-33 Newton iterations at 1, 3-12 at 0.5; docs/grasp.md)."""
    from types import SimpleNamespace

    from handfe.grasp.config import SolverSpec
    from handfe.grasp.scene import GraspFE

    fake = _with_stick_history(_FakeUzawa(), anchors=True)  # mapping: lambda_t +1, anchors +2
    fake.wf = SimpleNamespace(solver=SolverSpec(max_augment=12, uzawa_tangential_relax=0.5))
    c = fake.contact
    fake.max_change = 20.0  # Newton follows the full normal update
    GraspFE.augment(fake)
    assert fake.tangential == [False]  # one update, no lambda_t <- t_T after the mapping
    assert fake.resolves == [(pytest.approx(10.0), True)]
    assert c.lambda_n.x.array[0] == 10.0
    assert np.all(c.lambda_t.x.array == 0.5) and np.all(c.u_ref.x.array == 1.0)
    assert not c.history_due


class _FakeMuscles:
    """Stand-in for :class:`handfe.grasp.scene.GraspFE` in the muscles mode: two released
    joints of one digit pressing on an object; the tissue/contact torque stiffens
    exponentially with the flexion past first contact (a pad), the ligaments are a linear
    spring, and the condensed tissue tangent is that torque's exact derivative."""

    def __init__(self, tau_muscle, coupling=0.0):
        from types import SimpleNamespace

        from handfe.grasp.config import SolverSpec

        self.joints = [SimpleNamespace(name="index_pip", digit="index"),
                       SimpleNamespace(name="index_dip", digit="index")]
        self.wf = SimpleNamespace(solver=SolverSpec(max_step_deg=2.0, muscle_steps=4,
                                                    dip_pip_coupling=coupling))
        self.kin = SimpleNamespace(lo=np.full(2, -10.0), hi=np.full(2, 90.0),
                                   clamp=lambda t: np.clip(t, -10.0, 90.0),
                                   skeleton=lambda t: np.array(t, dtype=float),
                                   motions=lambda sk: sk)
        self.lig = SimpleNamespace(torques=lambda m, sk, joints: -20.0 * np.radians(sk))
        self.contact = SimpleNamespace(uzawa=None, u_ref=None)  # frictionless: no switch
        self.solver = self.bc = None
        self.problem = SimpleNamespace(comm=None)
        self.theta = np.zeros(2)
        self.tau_muscle = np.asarray(tau_muscle, dtype=float)
        self.outer_iterations = self.cuts = 0
        self.steps: list = []
        self.log: list[str] = []
        self.at_limit = np.zeros(2, dtype=bool)
        self.coupled: list = []

    # tissue torque on each joint's distal bones: -a (exp(b x) - 1), x = flexion (rad)
    A, B = np.array([50.0, 30.0]), np.array([8.0, 10.0])

    def say(self, msg):
        self.log.append(msg)

    def _tissue(self, theta):
        return -self.A * np.expm1(self.B * np.radians(theta))

    def torques(self):
        t_tis = self._tissue(self.theta)
        t_lig = self.lig.torques(None, self.theta, None)
        g = self.tau_muscle + t_lig + t_tis
        t_cpl = np.zeros(2)
        for ip, idp, c in self.coupled:
            t_cpl[idp], t_cpl[ip] = -g[idp], c * g[idp]
        g = g + t_cpl
        scale = np.maximum.reduce([np.abs(self.tau_muscle), np.abs(t_lig), np.abs(t_tis),
                                   np.abs(t_cpl)])
        return {"muscle": self.tau_muscle, "ligament": t_lig, "tissue": t_tis,
                "coupling": t_cpl, "residual": g, "relative": np.abs(g) / scale}

    def _coupling_matrix(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE._coupling_matrix(self)

    def _loose(self):  # Newton tolerances: nothing to loosen in a stand-in
        import contextlib

        return contextlib.nullcontext()

    def _tighten(self, *, stalled=False):
        pass

    def _close_digits(self):
        self.theta = np.array([2.0, 2.0])  # pressing lightly

    def _joint_geometry(self, skel):
        return [None, None], [None, None]

    def _go_to(self, theta, *, label, max_cuts=6):
        self.theta = np.array(theta, dtype=float)

    def _snapshot(self):
        return self.theta.copy()

    def _restore(self, snap):
        self.theta = snap.copy()

    def augment(self, *a, **k):
        pass

    def _friction_use(self):
        return "contact forces: -"

    def _penalty_to_pressure(self, **kw):
        from handfe.grasp.scene import GraspFE

        GraspFE._penalty_to_pressure(self, **kw)

    def _final_muscle_phase(self):
        from handfe.grasp.scene import GraspFE

        GraspFE._final_muscle_phase(self)

    def digit_forces(self):
        return {"index": float(-self._tissue(self.theta).sum() / 40.0)}

    def _balance_torques(self, rtol, *, label, uzawa_depth_mm=None):
        from handfe.grasp.scene import GraspFE

        return GraspFE._balance_torques(self, rtol, label=label, uzawa_depth_mm=uzawa_depth_mm)

    def _balance(self, rtol, *, label, uzawa_depth_mm=None):
        from handfe.grasp.scene import GraspFE

        return GraspFE._balance(self, rtol, label=label, uzawa_depth_mm=uzawa_depth_mm)

    def _grip_stall(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE._grip_stall(self)

    def _friction_history_per_load(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE._friction_history_per_load(self)

    def _set_limits(self, g):
        from handfe.grasp.scene import GraspFE

        GraspFE._set_limits(self, g)

    def _contact_data(self):
        return {"k": self.contact.k_n.value}

    def _set_contact_data(self, data):
        self.contact.k_n.value = data["k"]

    def _resolve(self, what, undo):  # the FE re-solve after a change of the contact data
        self.log.append(what)
        if getattr(self, "resolve_fails", False):
            undo()
            return False
        return True

    def _scale_stall_to_grip(self):
        from handfe.grasp.scene import GraspFE

        GraspFE._scale_stall_to_grip(self)


def _exact_tangent(monkeypatch, fake, factor=1.0):
    """The condensed torque tangent of a :class:`_FakeMuscles`: its tissue torque's exact
    derivative (times ``factor``, a tangent that over-predicts the response)."""
    import handfe.grasp.fe as fe

    monkeypatch.setattr(fe, "condensed_torque_jacobian", lambda *a: factor * np.diag(
        -fake.A * fake.B * np.exp(fake.B * np.radians(fake.theta))))


def _fake_muscles_run(monkeypatch, tau, coupling=0.0, tangent_factor=1.0):
    from handfe.grasp.scene import GraspFE

    fake = _FakeMuscles(tau, coupling)
    _exact_tangent(monkeypatch, fake, tangent_factor)
    GraspFE.solve_muscles(fake)
    return fake


def test_muscles_mode_balances_the_torques_by_homotopy_from_the_closed_posture(monkeypatch):
    tau = np.array([900.0, 400.0])  # N mm: far above what holds the lightly closed posture
    fake = _fake_muscles_run(monkeypatch, tau)
    tq = fake.torque
    assert np.all(tq["relative"] <= fake.wf.solver.torque_rtol)
    assert np.array_equal(fake.tau_muscle, tau)  # the applied torque is the muscle's at the end
    # the balance is the closed form: tau = a (exp(b x) - 1) + 20 x
    x = np.radians(fake.theta)
    assert np.allclose(fake.A * np.expm1(fake.B * x) + 20.0 * x, tau, rtol=2e-3)
    assert any("muscle load 0.250" in m for m in fake.log)


def test_muscles_mode_accepts_fe_stalls_relative_to_the_grip(monkeypatch):
    # the FE solves of the torque Newton accept a stall at <= muscle_stall_rtol x grip (the
    # stiff pads of the coarse cylinder stalled at 4e-3 - 9e-3 N at 88 N of grip), never
    # below the closing's absolute tolerance, and the tolerance is restored afterwards
    from types import SimpleNamespace

    from handfe.grasp.scene import GraspFE

    fake = _FakeMuscles(np.array([900.0, 400.0]))
    _exact_tangent(monkeypatch, fake)
    fake.solver = SimpleNamespace(stall_atol=1e-4)
    seen = []  # (stall tolerance, grip in N) at each FE move

    def go_to(theta, *, label, max_cuts=6):
        seen.append((fake.solver.stall_atol, sum(fake.digit_forces().values())))
        fake.theta = np.array(theta, dtype=float)

    fake._go_to = go_to
    GraspFE.solve_muscles(fake)
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    assert fake.solver.stall_atol == 1e-4
    # each move runs with the tolerance of the grip it starts from
    for tol, grip in seen:
        assert tol == pytest.approx(max(1e-4, 1e-4 * grip))
    assert max(g for _, g in seen) > 10.0  # N: the scaled tolerance was the one in force


@pytest.mark.parametrize("history", ["load", "iteration"])
def test_muscles_mode_friction_history_per_load_is_held_inside_each_balance(monkeypatch,
                                                                             history):
    # solver.muscle_friction_history = "load": every FE move of a load's torque Newton runs
    # with the return mapping held (_go_to then leaves it undone), and leaving the balance
    # marks the return mapping of the balanced state due, once per load; "iteration" holds
    # nothing (each accepted solve marks its own, in _go_to)
    from dataclasses import replace
    from types import SimpleNamespace

    from handfe.grasp.scene import GraspFE

    fake = _FakeMuscles(np.array([900.0, 400.0]))
    fake.wf = SimpleNamespace(solver=replace(fake.wf.solver, muscle_friction_history=history,
                                             muscle_frictionless_closing=False))
    _exact_tangent(monkeypatch, fake)
    marked = []
    fake.contact = SimpleNamespace(uzawa=None, u_ref="anchors",  # frictional
                                   on_step=lambda t, r, defer=False: marked.append(defer))
    fake._hold_history = False
    held = []

    def go_to(theta, *, label, max_cuts=6):
        held.append(fake._hold_history)
        fake.theta = np.array(theta, dtype=float)

    fake._go_to = go_to
    balances = []  # (the return mappings marked before it) per torque balance
    fake._balance = lambda rtol, *, label, uzawa_depth_mm=None: (
        balances.append(len(marked)),
        GraspFE._balance(fake, rtol, label=label, uzawa_depth_mm=uzawa_depth_mm))[1]
    GraspFE.solve_muscles(fake)
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    assert held and all(held) == (history == "load") and any(held) == (history == "load")
    assert not fake._hold_history
    assert len(balances) == 5  # four muscle loads, then the balance after the Uzawa phase
    assert marked == ([True] * len(balances) if history == "load" else [])
    if history == "load":
        assert balances == list(range(len(balances)))  # one mark as each balance ends


def test_muscles_mode_converges_when_the_tissue_gives_less_than_its_tangent(monkeypatch):
    # the condensed tangent says 6x the torque change the tissue then delivers (stick springs
    # on nodes that slip): plain Newton crawls at 1/6 of the remaining residual per iteration
    # and misses 1e-3 in max_outer = 30; the measured response ratio corrects the step
    tau = np.array([900.0, 400.0])
    fake = _fake_muscles_run(monkeypatch, tau, tangent_factor=6.0)
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    assert fake.cuts == 0 and fake.outer_iterations < 60
    assert any("tangent index x0.1" in m for m in fake.log)


def test_muscles_mode_failure_keeps_the_last_balanced_load(monkeypatch):
    # the FE solve fails beyond 20 deg of PIP flexion (as when a pad rolls off the object):
    # the homotopy halves its step until it gives up, and the state it leaves is the last
    # balanced load's, with the torque applied there (what run_workflow writes as partial)
    from handfe.errors import SolverError
    from handfe.grasp.scene import GraspFE

    class Failing(_FakeMuscles):
        def _go_to(self, theta, *, label, max_cuts=6):
            if theta[0] > 20.0:
                raise SolverError(f"{label}: Newton failed", load_step=1)
            super()._go_to(theta, label=label)

    fake = Failing([900.0, 400.0])
    _exact_tangent(monkeypatch, fake)
    with pytest.raises(SolverError, match="muscle load"):
        GraspFE.solve_muscles(fake)
    assert 0.0 < fake.muscle_load < 1.0 and fake.theta[0] <= 20.0
    tq = fake.torque
    assert np.all(tq["relative"] <= 10 * fake.wf.solver.torque_rtol)  # balanced there
    assert np.all(tq["muscle"] < [900.0, 400.0])                      # at part of the load
    assert fake.digit_force_N == fake.digit_forces()                   # of that state
    assert np.array_equal(fake.tau_muscle, [900.0, 400.0])


def test_muscles_mode_failed_final_phase_reports_the_balanced_full_load(monkeypatch):
    # the final Uzawa round moves the pads (here: 5 deg) and its re-balance fails: the state
    # reported (partial) is the balanced full load before that round, not the moved one (the
    # coarse cylinder's partial summary had relative torque residuals of 0.8-1.0 and 957 N of
    # grip that way)
    from handfe.errors import SolverError
    from handfe.grasp.scene import GraspFE

    class FailingFinal(_FakeMuscles):
        final = False

        def augment(self, *a, **k):
            self.final = True
            self.theta = self.theta + 5.0

        def _go_to(self, theta, *, label, max_cuts=6):
            if self.final:
                self.at_limit = np.ones(2, dtype=bool)  # end stops of a moved state
                raise SolverError(f"{label}: Newton failed", load_step=1)
            super()._go_to(theta, label=label)

    fake = FailingFinal([900.0, 400.0])
    _exact_tangent(monkeypatch, fake)
    with pytest.raises(SolverError, match="full muscle load"):
        GraspFE.solve_muscles(fake)
    assert fake.muscle_load == 1.0
    assert np.all(fake.torque["relative"] <= 10 * fake.wf.solver.torque_rtol)
    assert np.array_equal(fake.torque["muscle"], [900.0, 400.0])
    assert not fake.at_limit.any()  # the reported state's end stops, not the moved one's


def test_penalty_to_pressure_stiffens_only_when_asked_and_below_target():
    import dataclasses
    from types import SimpleNamespace

    from handfe.grasp.scene import GraspFE

    calls: list[float] = []

    def fake(on: bool, k: float, resolve_fails: bool = False, growth: float = 2.0):
        f = _FakeMuscles([900.0, 400.0])
        f.wf = SimpleNamespace(solver=dataclasses.replace(
            f.wf.solver, muscle_penalty_follows_pressure=on, muscle_penalty_growth=growth))
        kn = SimpleNamespace(value=k)

        def stiffen(k_new):
            calls.append(k_new)
            kn.value = k_new
            return 0.0

        f.contact = SimpleNamespace(uzawa=SimpleNamespace(peak_pressure=lambda: 0.2),
                                    adaptive_penalty=10.0, h_mm=2.0, k_n=kn, stiffen=stiffen)
        f.resolve_fails = resolve_fails
        return f

    # target: 0.2 MPa x max(10 / 2 mm, 1 / step_penetration_mm = 1 / 0.1 mm) = 2 N/mm3
    runs = [fake(True, 1.5), fake(True, 0.5),  # the second at most doubled per call
            fake(True, 2.5), fake(False, 0.5)]  # already stiffer; off
    for f in runs:
        GraspFE._penalty_to_pressure(f, resolve=True)
    assert calls == [pytest.approx(2.0), pytest.approx(1.0)]
    # stiffen keeps the nodal forces to ~1e-2 only: in the final phase the state is re-solved
    # with the stiffer penalty at once (one whose Uzawa updates all failed had reported the
    # unsolved state, 2.8 N out of balance); a failed re-solve gives the contact data back
    assert [sum("stiffer penalty" in m for m in f.log) for f in runs] == [1, 1, 0, 0]
    assert [f.contact.k_n.value for f in runs[:2]] == [pytest.approx(2.0), pytest.approx(1.0)]
    f = fake(True, 1.5, resolve_fails=True)
    GraspFE._penalty_to_pressure(f, resolve=True)
    assert f.contact.k_n.value == 1.5
    f = fake(True, 1.5)  # before a muscle load: the torque step's FE solve does it
    GraspFE._penalty_to_pressure(f)
    assert f.contact.k_n.value == pytest.approx(2.0)
    assert not any("stiffer penalty" in m for m in f.log)
    f = fake(True, 0.25, growth=4.0)  # solver.muscle_penalty_growth: 4x per call, not 2x
    GraspFE._penalty_to_pressure(f)
    assert f.contact.k_n.value == pytest.approx(1.0)
    f = fake(True, 0.25, growth=100.0)  # ... and never beyond the target
    GraspFE._penalty_to_pressure(f)
    assert f.contact.k_n.value == pytest.approx(2.0)


def test_muscles_mode_retries_a_failed_load_with_the_last_balanced_penalty(monkeypatch):
    # the pressure-following penalty doubles before each load; a load that fails is retried
    # (halved) with the penalty of the last balanced load, not doubled again (the coarse
    # cylinder with muscle_uzawa failed each retry's first step, cut to 1/4096, at 5.03 N/mm3)
    import dataclasses
    from types import SimpleNamespace

    from handfe.grasp.scene import GraspFE

    class Stiffening(_FakeMuscles):
        def __init__(self, tau):
            super().__init__(tau)
            self.wf = SimpleNamespace(solver=dataclasses.replace(
                self.wf.solver, muscle_penalty_follows_pressure=True))
            kn = SimpleNamespace(value=1.0)

            def stiffen(k_new):
                kn.value = k_new
                return 0.0

            self.contact = SimpleNamespace(
                uzawa=SimpleNamespace(peak_pressure=lambda: 100.0, penetration=lambda: 0.0),
                u_ref=None, adaptive_penalty=10.0, h_mm=2.0, k_n=kn, stiffen=stiffen)
            self.tried: list[tuple[str, float]] = []
            self.failed = False

        def _snapshot(self):
            return self.theta.copy(), self.contact.k_n.value

        def _restore(self, snap):
            self.theta, self.contact.k_n.value = snap[0].copy(), snap[1]

        def _balance_torques(self, rtol, *, label):
            self.tried.append((label, self.contact.k_n.value))
            if label == "muscle load 0.5" and not self.failed:
                self.failed = True
                return False, "FE solve failed"
            return super()._balance_torques(rtol, label=label)

    fake = Stiffening([900.0, 400.0])
    _exact_tangent(monkeypatch, fake)
    GraspFE.solve_muscles(fake)
    assert fake.tried[:4] == [("muscle load 0.25", 2.0), ("muscle load 0.5", 4.0),
                              ("muscle load 0.375", 2.0), ("muscle load 0.5", 4.0)]
    assert fake.muscle_load == 1.0


def test_muscles_mode_frictionless_closing_switches_friction_around_the_closing(monkeypatch):
    """``muscle_frictionless_closing``: the closing (and its tight solve) runs at mu = 0, the
    stick anchors are then set on the closed state, and the torque homotopy runs at the
    grasp's mu; a closing that fails leaves mu restored."""
    import dataclasses
    from types import SimpleNamespace

    from handfe.errors import SolverError
    from handfe.grasp.scene import GraspFE

    events: list = []

    def fake_run(fail: bool):
        fake = _FakeMuscles(np.array([900.0, 400.0]))
        fake.wf = SimpleNamespace(solver=dataclasses.replace(
            fake.wf.solver, muscle_frictionless_closing=True))
        c = SimpleNamespace(uzawa=None, u_ref=object(), mu=0.74)

        def set_friction(mu):
            c.mu = mu
            events.append(("mu", mu))

        c.set_friction = set_friction
        c.release_stick = lambda: events.append(("release", c.mu))
        c.on_step = lambda t, r, defer=False: None  # the friction history (held per load)
        fake.contact = c
        close, tighten = fake._close_digits, fake._tighten

        def closing():
            events.append(("close", c.mu))
            if fail:
                raise SolverError("closing step 3: Newton failed", load_step=3)
            close()

        fake._close_digits = closing
        fake._tighten = lambda **kw: (events.append(("tighten", c.mu)), tighten(**kw))[1]
        _exact_tangent(monkeypatch, fake)
        GraspFE.solve_muscles(fake)
        return fake

    fake = fake_run(fail=False)
    assert events[:5] == [("mu", 0.0), ("close", 0.0), ("tighten", 0.0), ("mu", 0.74),
                          ("release", 0.74)]
    assert fake.contact.mu == 0.74 and fake.closing_mu == 0.0  # summary.json's closing_mu
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    events.clear()
    with pytest.raises(SolverError, match="closing step 3"):
        fake_run(fail=True)
    assert events == [("mu", 0.0), ("close", 0.0), ("mu", 0.74)]


def test_response_ratios():
    from handfe.grasp.scene import response_ratios

    pred = np.array([10.0, -20.0, 1e-14, 0.0])
    act = np.array([2.0, -4.0, 5.0, 1.0])
    r = response_ratios(pred, act, ["a", "a", "b", "b"], {"a": 0.4, "b": 0.3})
    assert r["a"] == pytest.approx(0.2) and r["b"] == 0.3   # b: nothing predicted, kept
    assert response_ratios(pred, 3 * pred, ["a", "a", "b", "b"], {})["a"] == 1.0  # clipped
    # at most halved per step, never below 0.05
    assert response_ratios(pred, -pred, ["a", "a", "b", "b"], {})["a"] == 0.5
    assert response_ratios(pred, -pred, ["a", "a", "b", "b"], {"a": 0.08})["a"] == 0.05


def test_muscles_mode_more_flexor_force_never_lowers_the_contact_force(monkeypatch):
    base = _fake_muscles_run(monkeypatch, [900.0, 400.0]).digit_forces()["index"]
    more = _fake_muscles_run(monkeypatch, [990.0, 440.0]).digit_forces()["index"]
    assert more > base


def test_muscles_mode_dip_pip_coupling_balances_the_coupled_coordinate(monkeypatch):
    tau = np.array([900.0, 400.0])
    fake = _fake_muscles_run(monkeypatch, tau, coupling=2.0 / 3.0)
    assert fake.coupled == [(0, 1, 2.0 / 3.0)]
    # the DIP moved by 2/3 of the PIP's change from the closed posture (2, 2 deg)
    d = fake.theta - 2.0
    assert d[1] == pytest.approx(2.0 / 3.0 * d[0], rel=1e-9)
    tq = fake.torque
    assert np.all(tq["relative"] <= fake.wf.solver.torque_rtol)
    # the coupling takes the DIP's imbalance and passes 2/3 of it to the PIP (no net work)
    raw = tau + tq["ligament"] + tq["tissue"]
    assert tq["coupling"][1] == pytest.approx(-raw[1])
    assert raw[0] + 2.0 / 3.0 * raw[1] == pytest.approx(0.0, abs=1e-3 * np.abs(tau).max())


class _FakePinch(_FakeMuscles):
    """Two digits (one joint each) pinch an object free to move along x: the thumb pad
    presses it along +x, the index pad along -x, each with a force a (exp(b x) - 1) of its
    indentation x = theta (rad) -/+ t_x / r; the pad forces act on r = 20 mm levers; along y
    and z the object sits on stick springs (10 N/mm). Stiff ligaments (2000 N mm/rad): with a
    free object the digits and the object swing together at no cost to the pads, and only
    the ligaments take up the two muscles' difference. The condensed tangent is exact."""

    r, a, b, k_yz = 20.0, 2.0, 12.0, 10.0

    def __init__(self, tau_muscle, free=True):
        from types import SimpleNamespace

        super().__init__(tau_muscle)
        self.joints = [SimpleNamespace(name="thumb_mcp", digit="thumb"),
                       SimpleNamespace(name="index_mcp", digit="index")]
        self.grasp = SimpleNamespace(digits=("thumb", "index"))
        self.object_free = free
        self.contact = SimpleNamespace(uzawa=None, u_ref=None, translation=SimpleNamespace(
            value=np.zeros(3)))
        self.force_target = np.zeros(3)
        self._t_response: list = []
        self.lig = SimpleNamespace(torques=lambda m, sk, joints: -2000.0 * np.radians(sk))

    def _pads(self, theta, t):
        x = np.radians(theta) + np.array([-1.0, 1.0]) * t[0] / self.r
        return self.a * np.expm1(self.b * x), self.a * self.b * np.exp(self.b * x)

    def _tissue(self, theta):
        return -self.r * self._pads(theta, self.contact.translation.value)[0]

    def _contact_force_sums(self):
        # (net force on the object, each digit's force vector), N; the y/z springs stand
        # in for the rest of the skin
        F, _ = self._pads(self.theta, self.contact.translation.value)
        t = self.contact.translation.value
        net = np.array([F[0] - F[1], -self.k_yz * t[1], -self.k_yz * t[2]])
        return net, np.array([[F[0], 0.0, 0.0], [-F[1], 0.0, 0.0]])

    def object_residual(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE.object_residual(self)

    def digit_forces(self):
        from handfe.grasp.scene import GraspFE

        return GraspFE.digit_forces(self)

    def tangent(self, *a, translate=False):
        from handfe.grasp.fe import CondensedTangent

        _, dF = self._pads(self.theta, self.contact.translation.value)
        s = np.array([-1.0, 1.0]) / self.r  # d(indentation)/d(t_x)
        T = CondensedTangent(torque_theta=np.diag(-self.r * dF))
        T.torque_t = np.zeros((2, 3))
        T.torque_t[:, 0] = -self.r * dF * s
        T.force_theta = np.zeros((3, 2))
        T.force_theta[0] = [dF[0], -dF[1]]
        T.force_t = np.diag([dF[0] * s[0] - dF[1] * s[1], -self.k_yz, -self.k_yz])
        return T

    def _go_to(self, theta, *, label, max_cuts=6, translation=None):
        self.theta = np.array(theta, dtype=float)
        if translation is not None:
            self.contact.translation.value = np.array(translation, dtype=float)

    def _snapshot(self):
        return self.theta.copy(), self.contact.translation.value.copy()

    def _restore(self, snap):
        self.theta, self.contact.translation.value = snap[0].copy(), snap[1].copy()

    def _loose(self):  # Newton tolerances: nothing to loosen in a stand-in
        import contextlib

        return contextlib.nullcontext()

    def _tighten(self, *, stalled=False):
        pass

    def _close_digits(self):
        self.theta = np.array([1.0, 1.0])  # both pads pressing lightly, balanced

    def _friction_use(self):
        return "contact forces: -"


def test_muscles_mode_free_object_moves_until_the_digits_balance_on_it(monkeypatch):
    # the thumb's muscles pull twice as hard as the index's: with the object free, it moves
    # towards the index until both pads push equally (net force 0, every torque balanced);
    # held in space, the object takes the difference
    import handfe.grasp.fe as fe
    from handfe.grasp.scene import GraspFE

    tau = np.array([1200.0, 600.0])
    fake = _FakePinch(tau)
    monkeypatch.setattr(fe, "condensed_tangent", fake.tangent)
    GraspFE.solve_muscles(fake)
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    assert not fake.at_limit.any()
    f, grip = fake.object_residual()
    assert np.linalg.norm(f) <= fake.wf.solver.torque_rtol * grip
    F = fake.digit_forces()
    assert F["thumb"] == pytest.approx(F["index"], rel=2e-3)
    assert fake.contact.translation.value[0] > 1.0  # pushed (+x) towards the index
    assert any("object (mm)" in m for m in fake.log)

    held = _FakePinch(tau, free=False)
    monkeypatch.setattr(fe, "condensed_torque_jacobian", lambda *a: held.tangent().torque_theta)
    GraspFE.solve_muscles(held)
    F = held.digit_forces()
    assert np.all(held.torque["relative"] <= held.wf.solver.torque_rtol)
    assert F["thumb"] > 1.5 * F["index"]  # the support carries the difference
    assert np.array_equal(held.contact.translation.value, np.zeros(3))


def test_muscles_mode_uzawa_updates_within_the_balance(monkeypatch):
    # with muscle_uzawa, a torque step that leaves the pads deeper than step_penetration_mm is
    # followed by one Uzawa update; a load counts as balanced only with the pads within it
    from dataclasses import replace

    from handfe.grasp.scene import GraspFE

    fake = _FakeMuscles([900.0, 400.0])
    fake.wf.solver = replace(fake.wf.solver, muscle_uzawa=True, step_penetration_mm=0.1)
    depth = {"mm": 1.0}
    calls: list[tuple] = []

    def augment(tol_mm=None, *, creep=True, stop=None, max_updates=None, max_depth_mm=0.0):
        if max_updates is None:  # the final Uzawa phase at full load
            depth["mm"] = 0.005
            return
        assert max_updates == 1  # one update, then stop
        calls.append((tol_mm, creep))
        depth["mm"] = max(0.5 * depth["mm"], 0.05)  # each update halves the depth

    fake.contact.uzawa = type("U", (), {"penetration": lambda self: depth["mm"]})()
    fake.augment = augment
    fake._one_uzawa_update = lambda d: GraspFE._one_uzawa_update(fake, d)
    _exact_tangent(monkeypatch, fake)
    ends = []
    balance = fake._balance_torques

    def spy(rtol, *, label, uzawa_depth_mm=None):
        depth["mm"] = 1.0  # a new load sinks the pads in again
        ok, why = balance(rtol, label=label, uzawa_depth_mm=uzawa_depth_mm)
        ends.append(depth["mm"])
        return ok, why

    fake._balance_torques = spy
    GraspFE.solve_muscles(fake)
    assert calls and set(calls) == {(0.1, False)}
    assert max(ends) <= 0.1  # every balanced load ended within step_penetration_mm
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)


def test_muscles_mode_interleaved_final_phase_updates_between_torque_steps(monkeypatch):
    # muscle_final_uzawa = "interleaved": no Uzawa phase at the fixed posture after the full
    # load; the final balance takes one update (penetration only, to penetration_tol_mm)
    # after its torque steps and ends balanced with the pads within the tolerance
    from dataclasses import replace

    from handfe.grasp.scene import GraspFE

    fake = _FakeMuscles([900.0, 400.0])
    fake.wf.solver = replace(fake.wf.solver, muscle_final_uzawa="interleaved",
                             penetration_tol_mm=0.01)
    depth = {"mm": 1.2}
    calls: list[tuple] = []

    def augment(tol_mm=None, *, creep=True, stop=None, max_updates=None, max_depth_mm=0.0):
        assert max_updates == 1, "no Uzawa phase at the fixed posture"
        calls.append((tol_mm, creep))
        if depth["mm"] > tol_mm:
            depth["mm"] *= 0.4

    fake.contact.uzawa = type("U", (), {"penetration": lambda self: depth["mm"]})()
    fake.augment = augment
    fake._one_uzawa_update = lambda d: GraspFE._one_uzawa_update(fake, d)
    tight = []
    fake._tighten = lambda *, stalled=False: tight.append(stalled)
    resolves: list[bool] = []
    fake._penalty_to_pressure = lambda resolve=False: resolves.append(resolve)
    _exact_tangent(monkeypatch, fake)
    GraspFE.solve_muscles(fake)
    # the final state is solved tight (its FE solves may have stopped at a grip-scaled stall)
    assert tight[-1] is True
    assert len(calls) >= 5 and set(calls) == {(0.01, False)}
    assert depth["mm"] <= 0.01
    assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
    # the penalty follows the pressure before each load, but is not raised and re-solved at the
    # fixed posture before the interleaved phase (that re-solve failed on the coarse cylinder
    # in runs C, D, E); the fixed phase still does it
    assert resolves and not any(resolves)
    fixed = _FakeMuscles([900.0, 400.0])
    fixed._penalty_to_pressure = lambda resolve=False: resolves.append(resolve)
    _exact_tangent(monkeypatch, fixed)
    GraspFE.solve_muscles(fixed)
    assert resolves[-1] is True


def test_muscle_uzawa_rtol_lets_the_torques_catch_up_before_an_update(monkeypatch):
    # each Uzawa update of the interleaved final phase hardens the pad (here: the tissue
    # torque 1.3x stiffer), which raises the torque residual; with muscle_uzawa_rtol the next
    # update waits until the torque Newton has brought it back under that, without it one
    # follows every torque step
    from dataclasses import replace

    from handfe.grasp.scene import GraspFE

    def run(gate: float):
        fake = _FakeMuscles([900.0, 400.0])
        fake.wf.solver = replace(fake.wf.solver, muscle_final_uzawa="interleaved",
                                 penetration_tol_mm=0.01, muscle_uzawa_rtol=gate)
        depth = {"mm": 1.2}
        at_update: list[float] = []

        def augment(tol_mm=None, *, creep=True, stop=None, max_updates=None,
                    max_depth_mm=0.0):
            at_update.append(float(fake.torques()["relative"].max()))
            if depth["mm"] > tol_mm:
                depth["mm"] *= 0.4
                fake.A = fake.A * 1.3

        fake.contact.uzawa = type("U", (), {"penetration": lambda self: depth["mm"]})()
        fake.augment = augment
        fake._one_uzawa_update = lambda d: GraspFE._one_uzawa_update(fake, d)
        fake._penalty_to_pressure = lambda resolve=False: None
        _exact_tangent(monkeypatch, fake)
        GraspFE.solve_muscles(fake)
        assert depth["mm"] <= 0.01
        assert np.all(fake.torque["relative"] <= fake.wf.solver.torque_rtol)
        return at_update

    gated = run(0.05)
    assert len(gated) >= 5 and max(gated) <= 0.05
    assert max(run(0.0)) > 0.05  # ungated: an update right after a step


def test_friction_demand_matches_a_dense_search_and_a_closed_form():
    from handfe.grasp.mechanics import friction_demand

    # a planar two-joint chain (axes e_z): the in-plane force is fixed, F_z is free
    A = np.array([[0.0, 10.0, 0.0], [-5.0, 20.0, 0.0]])  # rows a_j x (p - c_j), mm
    F_plane = np.array([3.0, 4.0, 0.0])
    b = A @ F_plane
    n = np.array([0.0, 1.0, 0.0])
    r, F = friction_demand(A, b, n)
    assert r == pytest.approx(3.0 / 4.0, rel=1e-9)  # F_z = 0 is the least tangential force
    assert np.allclose(A @ F, b)
    # a normal with an out-of-plane part: the free F_z helps; compare with a dense search
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = rng.normal(size=(2, 3))
        b = rng.normal(size=2)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        r, F = friction_demand(A, b, n, max_force_N=50.0)
        F0 = np.linalg.lstsq(A, b, rcond=None)[0]
        d = np.linalg.svd(A)[2][-1]
        s = np.linspace(-60.0, 60.0, 240001)
        Fs = F0[None, :] + s[:, None] * d[None, :]
        fn = Fs @ n
        ok = (fn > 0) & (np.linalg.norm(Fs, axis=1) <= 50.0)
        brute = (np.linalg.norm(Fs - fn[:, None] * n[None, :], axis=1)[ok] / fn[ok]).min() \
            if ok.any() else np.inf
        assert r == pytest.approx(brute, rel=1e-4, abs=1e-9)
        if np.isfinite(r):
            assert np.allclose(A @ F, b) and np.linalg.norm(F) <= 50.0 + 1e-9


def test_friction_use_names_a_digit_off_the_object():
    """The stall message of the torque balance: each digit's tangential/normal against mu;
    a digit without contact force is named as off the object (not a ratio of nan)."""
    from types import SimpleNamespace

    from handfe.grasp.scene import GraspFE

    reg = {"thumb": {"normal_force_N": 0.0, "tangential_force_N": 0.0},
           "index": {"normal_force_N": 5.0, "tangential_force_N": 3.6}}
    fake = SimpleNamespace(metrics=lambda: (reg, None),
                           grasp=SimpleNamespace(friction=0.74, digits=("thumb", "index")))
    msg = GraspFE._friction_use(fake)
    assert msg == ("contact forces (mu = 0.74): thumb 0 N (off the object), "
                   "index 5.00 N, tangential/normal 0.72 (at the friction limit)")


def test_balance_problems_name_what_is_off():
    """A finished run is "done" only if the object force meets the support reactions (1e-6)
    and, muscle-driven, every released joint off its limits balances to torque_rtol (run G of
    the coarse cylinder: equilibrium 1.7e-14 after the tight solve, torque residual 2.1e-3)."""
    ok = {"equilibrium_relative_error": 1e-9, "max_relative_torque_residual": 5e-4}
    assert balance_problems(ok, "muscles", 1e-3) == []
    run_g = {"equilibrium_relative_error": 1.7e-14, "max_relative_torque_residual": 2.1e-3}
    (msg,) = balance_problems(run_g, "muscles", 1e-3)
    assert "torque residual 0.0021" in msg and "solver.torque_rtol" in msg
    # the angles mode's joint torques are reactions, not a balance
    assert balance_problems(run_g, "angles", 1e-3) == []
    run_f = {"equilibrium_relative_error": 6.1e-5, "max_relative_torque_residual": 9.5e-4}
    (msg,) = balance_problems(run_f, "muscles", 1e-3)
    assert "object force vs support reactions 6.1e-05" in msg
    assert len(balance_problems({"equilibrium_relative_error": float("nan")}, "angles",
                                1e-3)) == 1


def test_the_muscles_mode_says_up_front_what_it_has_shown_for_the_grasp_and_mesh():
    """A muscle-driven run other than one that has run to the end with its recipe's keys
    starts with a note of what that combination has shown (docs/grasp.md), so that a user
    does not wait 40 minutes for a known failure; the angles mode and the finished recipes get
    none, but for a recipe's record of whole runs that did not finish; with the object free
    (solver.free_object) a grasp and level where that has not run to the end get their own."""
    from handfe.grasp.scene import FREE_OBJECT_DONE, FULL_LOAD_RECIPES, muscles_mode_caveat

    assert muscles_mode_caveat("angles", "spherical", "reduced") == ""
    assert muscles_mode_caveat("muscles", "cylindrical", "coarse") == ""
    reduced = muscles_mode_caveat("muscles", "cylindrical", "reduced")
    assert "('done') only as: cylindrical at 'coarse' (workflows/cylindrical_muscles.toml)" \
        in reduced
    assert "failed the first quarter of the load" in reduced and "partial" in reduced
    assert "cylindrical at 'reduced' with solver.guard_damping = true and " \
        "solver.muscle_stall_rtol >= 3e-4 (workflows/cylindrical_muscles_reduced.toml)" \
        in reduced
    # each recipe's file ships the keys its entry says; with them no caveat, one of them
    # short of it: the caveat
    for (grasp, level), entry in FULL_LOAD_RECIPES.items():
        recipe = load_workflow(REPO_ROOT / "workflows" / entry.workflow)
        assert (recipe.grasp, recipe.mesh, recipe.loading, recipe.muscle_force_scale) == \
            (grasp, level, "muscles", 1.0)
        assert entry.met_by(recipe.solver)
        assert f"(workflows/{entry.workflow})" in reduced
        met = muscles_mode_caveat("muscles", grasp, level, recipe.solver)
        # a recipe that did not run to the end every time says so
        assert met == "" if not entry.record else \
            (entry.record in met and f"workflows/{entry.workflow}" in met)
        for key, off in (("guard_damping", False), ("muscle_stall_rtol", 1e-4),
                         ("inversion_guard", 0.1)):
            if getattr(entry, key) and getattr(entry, key) != off:
                short = dataclasses.replace(recipe.solver, **{key: off})
                assert f"; {grasp} at '{level}' " in muscles_mode_caveat("muscles", grasp,
                                                                         level, short)
    recipe = load_workflow(REPO_ROOT / "workflows" / "cylindrical_muscles_reduced.toml")
    undamped = dataclasses.replace(recipe.solver, guard_damping=False)
    assert muscles_mode_caveat("muscles", "cylindrical", "reduced", undamped) == reduced
    full = muscles_mode_caveat("muscles", "precision", "coarse", recipe.solver)
    assert "38-53 %" in full and "at muscle_force_scale <= 0.1 it ran to the end" in full
    assert "friction limit" in full
    assert "at the full EMG load" in full
    # a light grip where one has run to the end: no caveat; heavier: the caveat
    assert muscles_mode_caveat("muscles", "precision", "coarse", recipe.solver, 0.1) == ""
    assert muscles_mode_caveat("muscles", "precision", "coarse", recipe.solver, 0.5) == full
    assert "has not been run" in muscles_mode_caveat("muscles", "precision", "default", None,
                                                     0.1)
    assert muscles_mode_caveat("muscles", "spherical", "coarse", recipe.solver, 0.1) == ""
    # the object free: where that ran to the end, the held object's caveat; elsewhere its own
    free = dataclasses.replace(recipe.solver, free_object=True)
    assert muscles_mode_caveat("muscles", "cylindrical", "coarse", free) == ""
    for (grasp, level), name in FREE_OBJECT_DONE.items():
        wf = load_workflow(REPO_ROOT / "workflows" / name)
        assert (wf.grasp, wf.mesh, wf.solver.free_object) == (grasp, level, True)
    pinch = muscles_mode_caveat("muscles", "precision", "coarse", free, 0.1)
    assert "object free" in pinch and "1/64" in pinch and "cylindrical_muscles_free" in pinch
    assert "has not been run" in muscles_mode_caveat("muscles", "cylindrical", "reduced", free)
    assert "1/64" in muscles_mode_caveat("muscles", "spherical", "coarse", free)
    ball = muscles_mode_caveat("muscles", "spherical", "coarse", recipe.solver, 0.25)
    assert "final contact phase" in ball and "<= 0.1 it ran to the end" in ball
    assert "solver.inversion_guard >= 0.5" in ball and "spherical_muscles.toml" in ball
    assert "one of two whole runs" in FULL_LOAD_RECIPES["spherical", "coarse"].record

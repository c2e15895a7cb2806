"""The MuJoCo body: generated from the .osim, laid out as the env expects, faithful in geometry."""

import json

import mujoco
import numpy as np
import pytest

from l2r.sim import convert, fit, model as body, opensim

REFERENCE = json.loads((convert.ASSETS / "opensim_reference.json").read_text())


@pytest.fixture(scope="module")
def m() -> mujoco.MjModel:
    return body.load_model()


@pytest.fixture(scope="module")
def osim() -> opensim.Osim:
    return opensim.read_osim(convert.OSIM_PATH)


@pytest.fixture(scope="module")
def generated() -> str:
    return convert.generate(convert.OSIM_PATH)  # the whole conversion, fits included (seconds)


def test_converter_reproduces_the_committed_model(generated):
    assert generated == convert.MJCF_PATH.read_text()


def test_check_flags_a_stale_model(generated, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(convert, "generate", lambda path, progress=None: generated)  # reuse the conversion above
    assert convert.main(["--check"]) == 0
    stale = tmp_path / "runner.xml"
    stale.write_text(generated.replace('mass="34.2366"', 'mass="34.2"'))
    assert convert.main(["--check", "--out", str(stale)]) == 1
    assert "differs" in capsys.readouterr().err
    assert convert.main(["--out", str(stale)]) == 0
    assert stale.read_text() == generated


def test_converter_rejects_a_file_that_is_not_an_osim_model(tmp_path, capsys):
    bad = tmp_path / "bad.osim"
    bad.write_text("<OpenSimDocument><Nothing/></OpenSimDocument>")
    assert convert.main(["--osim", str(bad), "--out", str(tmp_path / "out.xml")]) == 2
    assert "no <Model>" in capsys.readouterr().err
    bad.write_text("<not xml")
    assert convert.main(["--osim", str(bad), "--out", str(tmp_path / "out.xml")]) == 2


def test_masses_come_from_the_osim(m):
    assert m.body_mass.sum() == pytest.approx(79.6646, abs=1e-6)
    assert m.body_mass.sum() == pytest.approx(REFERENCE["facts"]["total_mass"], abs=0.01)
    for b in REFERENCE["facts"]["bodies"]:
        assert m.body(b["name"]).mass[0] == pytest.approx(b["mass"])
        np.testing.assert_allclose(m.body(b["name"]).ipos, b["mass_center"], atol=1e-9)


def test_joint_layout_follows_the_osim_coordinates(m):
    slides = {"pelvis_tx", "pelvis_ty", "knee_tx_r", "knee_ty_r", "knee_tx_l", "knee_ty_l"}
    names = {m.joint(j).name for j in range(m.njnt)}
    assert names == set(body.COORDINATES) | slides
    for j in range(m.njnt):
        kind = mujoco.mjtJoint.mjJNT_SLIDE if m.joint(j).name in slides else mujoco.mjtJoint.mjJNT_HINGE
        assert m.jnt_type[j] == kind
    for b in body.BODIES:
        assert m.body(b).id > 0
    np.testing.assert_allclose(m.opt.gravity, [0, -9.80665, 0])
    assert round(0.01 / m.opt.timestep) * m.opt.timestep == pytest.approx(0.01)
    # the lumbar joint is welded at its locked value
    assert m.body("torso").jntnum[0] == 0
    angle = 2 * np.arctan2(m.body("torso").quat[3], m.body("torso").quat[0])
    assert angle == pytest.approx(-0.139626)


def test_default_pose_matches_the_2017_reset_observation(m):
    d = mujoco.MjData(m)
    body.reset_to_default(m, d)
    obs = REFERENCE["rollouts"][0]["reset_observation"]
    assert d.qpos[m.joint("pelvis_ty").qposadr[0]] == pytest.approx(0.91)
    assert d.qpos[m.joint("pelvis_tilt").qposadr[0]] == pytest.approx(-0.05)
    for i, name in enumerate(("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")):
        np.testing.assert_allclose(d.body(name).xpos[:2], obs[22 + 2 * i : 24 + 2 * i], atol=1e-6)
    np.testing.assert_allclose(d.subtree_com[0][:2], obs[18:20], atol=1e-6)


def test_muscles_are_actuators_in_action_order_with_thelen_parameters(m):
    assert tuple(m.actuator(i).name for i in range(m.nu)) == body.MUSCLES
    for i, fact in enumerate(REFERENCE["facts"]["muscles"]):
        a = m.actuator(fact["name"])
        assert a.trntype[0] == mujoco.mjtTrn.mjTRN_TENDON and m.tendon(a.trnid[0]).name == fact["name"]
        assert a.ctrllimited[0] and tuple(a.ctrlrange) == (0.0, 1.0)
        assert a.gainprm[2] == pytest.approx(fact["max_isometric_force"])
        # MuJoCo: L0 = (lengthrange1 - lengthrange0) / (range1 - range0), and the normalised
        # length range0 + (L - lengthrange0) / L0 is 1 at L = slack + optimal fibre length
        lr, rng = a.lengthrange, a.gainprm[:2]
        l0 = (lr[1] - lr[0]) / (rng[1] - rng[0])
        assert l0 == pytest.approx(fact["optimal_fiber_length"])
        assert lr[0] + (1 - rng[0]) * l0 == pytest.approx(fact["tendon_slack_length"] + fact["optimal_fiber_length"])
        assert a.gainprm[6] == pytest.approx(fact["max_contraction_velocity"])
        assert tuple(a.dynprm[:2]) == (fact["activation_time_constant"], fact["deactivation_time_constant"])


def test_feet_touch_ground_and_obstacles_but_not_each_other(m):
    def collide(a, b):
        ga, gb = m.geom(a), m.geom(b)
        return bool(ga.contype[0] & gb.conaffinity[0]) or bool(gb.contype[0] & ga.conaffinity[0])

    for foot in body.CONTACT_SPHERES:
        assert m.geom(foot).friction[0] == pytest.approx(0.8)
        assert collide(foot, body.GROUND)
        assert all(collide(foot, o) for o in body.OBSTACLES)
        assert not any(collide(foot, other) for other in body.CONTACT_SPHERES)
    for o in body.OBSTACLES:
        assert m.geom(o).bodyid[0] == 0 and m.geom(o).pos[1] < -1  # parked under the ground
    colliding = [g for g in range(m.ngeom) if m.geom_contype[g] or m.geom_conaffinity[g]]
    assert len(colliding) == 8  # four spheres, ground, three obstacles: nothing else costs time


def test_knee_translation_follows_the_osim_splines(m, osim):
    d = mujoco.MjData(m)
    body.reset_to_default(m, d)
    spline_x, spline_y = (f for _, _, f in osim.bodies["tibia_r"].joint.translations[:2])
    for angle in np.linspace(-2.09, 0.17, 12):
        body.set_pose(m, d, {"knee_angle_r": angle, "hip_flexion_r": 0.0})
        mujoco.mj_kinematics(m, d)
        offset = d.body("tibia_r").xpos - d.body("femur_r").xpos
        offset = d.body("femur_r").xmat.reshape(3, 3).T @ offset
        # the quartic coupling stays within 0.5 mm of the splines
        assert offset[0] == pytest.approx(float(spline_x(angle)), abs=5e-4)
        assert offset[1] == pytest.approx(float(spline_y(angle)), abs=5e-4)


def test_numpy_opensim_geometry_matches_opensim(osim):
    # the converter fits against this geometry, so it has to be OpenSim's own
    samples = REFERENCE["geometry"][:50]
    pose = {c: np.array([s["pose"][c] for s in samples]) for c in samples[0]["pose"]}
    for muscle in osim.muscles:
        ours = opensim.opensim_length(osim, muscle, pose)
        theirs = [s["muscles"][muscle.name]["mtu_length"] for s in samples]
        np.testing.assert_allclose(ours, theirs, atol=1e-9)


def test_numpy_thelen_matches_opensim_isometric_forces(osim):
    samples = REFERENCE["isometric_forces"]
    pose = {c: np.array([s["pose"][c] for s in samples]) for c in samples[0]["pose"]}
    for muscle in osim.muscles:
        length = opensim.opensim_length(osim, muscle, pose)
        for a in ("0.0", "0.5", "1.0"):
            theirs = np.array([s["forces"][muscle.name][a] for s in samples])
            ours = opensim.thelen_isometric_force(muscle, length, float(a))
            assert np.max(np.abs(ours - theirs)) < 0.01 * muscle.max_force, (muscle.name, a)


def test_converter_path_lengths_are_what_mujoco_computes(m, osim):
    # the fit measures paths with its own copy of MuJoCo's geometry (sites, cylinder wraps);
    # check that copy against MuJoCo on the fitted model
    rng = np.random.default_rng(0)
    d = mujoco.MjData(m)
    body.reset_to_default(m, d)
    paths = {}
    for muscle in osim.muscles:
        sites = [(m.site_bodyid[m.site(f"{muscle.name}_{i}").id], m.site(f"{muscle.name}_{i}").pos.copy()) for i in range(len(muscle.points)) if _has_site(m, f"{muscle.name}_{i}")]
        wrap = None
        if _has_geom(m, f"{muscle.name}_wrap"):
            g = m.geom(f"{muscle.name}_wrap")
            side = m.site(f"{muscle.name}_side").pos - g.pos
            wrap = (m.body(g.bodyid[0]).name, g.pos.copy(), float(g.size[0]), side / np.linalg.norm(side))
        t = m.tendon(muscle.name).id
        kinds = m.wrap_type[m.tendon_adr[t] : m.tendon_adr[t] + m.tendon_num[t]]
        wrap_after = next((k - 1 for k, kind in enumerate(kinds) if kind == mujoco.mjtWrap.mjWRAP_CYLINDER), 0)
        paths[muscle.name] = fit.MusclePath([(m.body(b).name, p) for b, p in sites], wrap, wrap_after)
    for _ in range(20):
        pose = {c: rng.uniform(-1.4, 1.4) for c in body.LEG_COORDINATES}
        pose["knee_angle_r"] = pose["knee_angle_l"] = rng.uniform(-1.5, 0.1)
        body.set_pose(m, d, pose)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        frames = opensim.body_frames(osim, {c: np.array([v]) for c, v in pose.items()}, fit.coupled_translations(osim))
        for name, path in paths.items():
            assert fit.path_length(frames, path)[0] == pytest.approx(d.ten_length[m.tendon(name).id], abs=1e-6), name


def _has_site(m, name):
    try:
        m.site(name)
        return True
    except KeyError:
        return False


def _has_geom(m, name):
    try:
        m.geom(name)
        return True
    except KeyError:
        return False

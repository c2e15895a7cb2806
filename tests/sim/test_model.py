"""The MuJoCo body: generated from the .osim, laid out as the env expects, faithful in geometry."""

import json

import mujoco
import numpy as np
import pytest

from l2r.sim import convert, model as body, opensim, thelen
from l2r.sim.paths import OFF, MovingPoints, PathSwitches
from tests.sim.knee_torques import STEP, knee_torque

REFERENCE = json.loads((convert.ASSETS / "opensim_reference.json").read_text())


@pytest.fixture(scope="module")
def m() -> mujoco.MjModel:
    return body.load_model()


@pytest.fixture(scope="module")
def osim() -> opensim.Osim:
    return opensim.read_osim(convert.OSIM_PATH)


@pytest.fixture(scope="module")
def generated() -> str:
    return convert.generate(convert.OSIM_PATH)


def test_converter_reproduces_the_committed_model(generated):
    assert convert.model_differences(convert.MJCF_PATH.read_text(), generated) == []


# What another CPU's fit makes of one path point (an AVX2 machine against the AVX-512 one that
# generated the model: y 1e-5 off), and changes the check must catch.
POINT = '<site name="iliopsoas_r_1" pos="-0.0238 -0.057 0.0759" />'
OTHER_CPU = POINT.replace("-0.057 ", "-0.05701 ")
MOVED_1_MM = POINT.replace("-0.057 ", "-0.058 ")


@pytest.mark.parametrize("edit, up_to_date", [
    ((POINT, OTHER_CPU), True),
    ((POINT, MOVED_1_MM), False),
    (('mass="34.2366"', 'mass="35"'), False),
    (('type="capsule"', 'type="sphere"'), False),
    ((POINT, ""), False),
])
def test_check_takes_another_cpus_last_digits_and_flags_a_stale_model(generated, tmp_path, monkeypatch, capsys,
                                                                      edit, up_to_date):
    monkeypatch.setattr(convert, "generate", lambda path, progress=None: generated)  # reuse the conversion above
    assert convert.main(["--check"]) == 0
    assert edit[0] in generated
    committed = tmp_path / "runner.xml"
    committed.write_text(generated.replace(*edit))
    assert convert.main(["--check", "--out", str(committed)]) == (0 if up_to_date else 1)
    assert ("differs" in capsys.readouterr().err) != up_to_date
    assert convert.main(["--out", str(committed)]) == 0
    assert committed.read_text() == generated


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


def test_actuators_are_muscle_tendons_then_contacts_then_second_paths(m, osim):
    """The first 18 actuators pull on the muscles' tendons in action order, with force set by the
    env (unlimited ctrl, an affine bias for the stiffness); then x and y forces per foot sphere;
    then the tendons without a conditional point; then the knees' moving-point work."""
    names = [m.actuator(i).name for i in range(m.nu)]
    contacts = [f"{s}_{axis}" for s in body.CONTACT_SPHERES for axis in "xy"]
    second = [mu.name + OFF for mu in osim.muscles if any(p.kind == "conditional" for p in mu.points)]
    assert names == list(body.MUSCLES) + contacts + second + ["knee_angle_l_moving_points", "knee_angle_r_moving_points"]
    for name in list(body.MUSCLES) + second:
        a = m.actuator(name)
        assert a.trntype[0] == mujoco.mjtTrn.mjTRN_TENDON and m.tendon(a.trnid[0]).name == name
        assert not a.ctrllimited[0] and a.biastype[0] == mujoco.mjtBias.mjBIAS_AFFINE
    for name in contacts:
        a = m.actuator(name)
        assert a.trntype[0] == mujoco.mjtTrn.mjTRN_SITE and m.site(a.trnid[0]).name == name[:-2] + "_contact"
        assert m.site(a.trnid[1]).bodyid[0] == 0  # against a world site: Cartesian forces


def test_thelen_parameters_are_the_osims(osim):
    table = thelen.muscle_parameters(osim.muscles)
    for row, fact in zip(table, REFERENCE["facts"]["muscles"]):
        assert row[thelen.MAX_FORCE] == pytest.approx(fact["max_isometric_force"])
        assert row[thelen.OPTIMAL_LENGTH] == pytest.approx(fact["optimal_fiber_length"])
        assert row[thelen.SLACK_LENGTH] == pytest.approx(fact["tendon_slack_length"])
        assert row[thelen.MAX_SPEED] == pytest.approx(fact["max_contraction_velocity"] * fact["optimal_fiber_length"])
        assert (row[thelen.TAU_ACTIVATION], row[thelen.TAU_DEACTIVATION]) == (fact["activation_time_constant"], fact["deactivation_time_constant"])


def test_mujoco_collides_nothing(m):
    """The env computes every force on the feet, the ground's and the obstacles': MuJoCo's
    collision detection is off and no geom could collide were it on."""
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not m.geom_contype.any() and not m.geom_conaffinity.any()
    for o in body.OBSTACLES:
        assert m.geom(o).bodyid[0] == 0 and m.geom(o).pos[1] < -1  # parked under the ground


def test_knee_translation_follows_the_osim_splines(m, osim):
    d = mujoco.MjData(m)
    body.reset_to_default(m, d)
    spline_x, spline_y = (f for _, _, f in osim.bodies["tibia_r"].joint.translations[:2])
    for angle in np.linspace(-2.09, 0.5, 14):  # hyperextension too
        body.set_pose(m, d, {"knee_angle_r": angle, "hip_flexion_r": 0.0})
        mujoco.mj_kinematics(m, d)
        offset = d.body("tibia_r").xpos - d.body("femur_r").xpos
        offset = d.body("femur_r").xmat.reshape(3, 3).T @ offset
        # the quartic coupling stays within 0.5 mm of the splines (extrapolated linearly)
        assert offset[0] == pytest.approx(float(spline_x(angle)), abs=5e-4)
        assert offset[1] == pytest.approx(float(spline_y(angle)), abs=5e-4)


def test_numpy_opensim_geometry_matches_opensim(osim):
    # the path tests below compare MuJoCo with this geometry, so it has to be OpenSim's own
    samples = REFERENCE["geometry"][:50]
    pose = {c: np.array([s["pose"][c] for s in samples]) for c in samples[0]["pose"]}
    for muscle in osim.muscles:
        ours = opensim.opensim_length(osim, muscle, pose)
        theirs = [s["muscles"][muscle.name]["mtu_length"] for s in samples]
        np.testing.assert_allclose(ours, theirs, atol=1e-9)


def test_thelen_equilibrium_matches_opensim_isometric_forces(osim):
    samples = REFERENCE["isometric_forces"]
    pose = {c: np.array([s["pose"][c] for s in samples]) for c in samples[0]["pose"]}
    table = thelen.muscle_parameters(osim.muscles)
    for i, muscle in enumerate(osim.muscles):
        length = opensim.opensim_length(osim, muscle, pose)
        for a in ("0.0", "0.5", "1.0"):
            theirs = np.array([s["forces"][muscle.name][a] for s in samples])
            ours = np.array([thelen.tendon_force(thelen.equilibrium_fiber_length(float(a), x, table[i]), x, table[i]) for x in length])
            assert np.max(np.abs(ours - theirs)) < 1e-4 * muscle.max_force, (muscle.name, a)


def test_mujoco_paths_are_opensims_in_every_pose(m, osim):
    """With the tendon each conditional point selects and the moving points placed, MuJoCo's
    muscle-tendon lengths are OpenSim's to within the knee coupling's fit, from deep flexion
    to hyperextension, and the moving points' work makes MuJoCo's generalised force -F dL/dq."""
    rng = np.random.default_rng(0)
    d = mujoco.MjData(m)
    switches, moving = PathSwitches(m, osim.muscles), MovingPoints(m, osim, osim.muscles)
    for _ in range(40):
        body.reset_to_default(m, d)
        pose = {c: rng.uniform(-1.5, 1.5) for c in body.LEG_COORDINATES}
        pose["knee_angle_r"], pose["knee_angle_l"] = rng.uniform(-2.5, 0.5, 2)
        body.set_pose(m, d, pose)
        moving.place(m, d.qpos)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        ours = d.ten_length[switches.tendons(d.qpos)]
        theirs = [opensim.opensim_length(osim, mu, {c: np.array([v]) for c, v in pose.items()})[0] for mu in osim.muscles]
        np.testing.assert_allclose(ours, theirs, atol=6e-4)


@pytest.mark.parametrize("knee", [-1.2, -0.4, 0.1])
def test_moving_points_add_the_work_of_their_motion(m, osim, knee):
    """OpenSim's generalised force of a muscle with a moving point is -F dL/dq along the knee;
    MuJoCo's tendon moment arm holds the site fixed, and the knee's moving-point actuator adds
    the rest. Checked for vasti and rectus femoris against OpenSim's lengths."""
    moving, switches = MovingPoints(m, osim, osim.muscles), PathSwitches(m, osim.muscles)
    for name in ("vasti_r", "rect_fem_r"):
        index, muscle = next((i, mu) for i, mu in enumerate(osim.muscles) if mu.name == name)
        lengths = [opensim.opensim_length(osim, muscle, {"knee_angle_r": np.array([knee + s]), "hip_flexion_r": np.array([0.3])})[0] for s in (STEP, -STEP)]
        dl_dq = (lengths[0] - lengths[1]) / (2 * STEP)
        generalised, share = knee_torque(m, moving, switches, index, {"knee_angle_r": knee, "hip_flexion_r": 0.3})
        assert abs(share) > 1.0  # the term matters
        # within half a millimetre of moment arm
        assert generalised == pytest.approx(-1000.0 * dl_dq, abs=0.5), name

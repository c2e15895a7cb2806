"""The feet on the ground and on the obstacles as OpenSim's `HuntCrossleyForce` pushes them
(Simbody's law).

For a sphere of radius R sunk d into the ground at penetration rate v_n (positive going in):
    f_H = 4/3 · k · d · sqrt(R · k · d),   k = stiffness^(2/3) / 2  (two equally stiff surfaces)
    f   = f_H · (1 + 3/2 · c · v_n),       normal force max(f, 0)
    friction = f · (min(s, 1) · (μd + 2 (μs - μd) / (1 + s²)) + μv · |v_t|),   s = |v_t| / v_transition
against the slip v_t of the contact point, which lies midway between the sphere's lowest point
and the ground. While f < 0 (the sphere leaving faster than the dissipation allows) there is no
force at all: Simbody's formula would turn friction around there, but OpenSim 4.6 applies none
(measured: the toe's friction reads 0 in OpenSim's records where this formula gives 450 N).
Nor does it apply any to the contacts listed after that one in the same force element: Simbody's
HuntCrossleyForce returns from its loop over an element's contacts at the first whose force is
not positive. Each foot is one element (`foot_r`: its heel and toe spheres), its contacts listed
in the order of a sweep along x, where the runner's feet lie, by each sphere's rearmost x: so a
heel leaving the ground fast takes the force off its toe, though the toe still presses (measured
in OpenSim at a two-footed push-off: both toes' 853 and 631 N gone as their heels left, the toes
unmoved; docs/model.md).

The env applies each force through two MuJoCo actuators on a site it moves to the contact point
(one along x, one along y, against a world site), and hands MuJoCo's implicit integrator the
force's derivative with respect to the contact point's speed as actuator damping: the friction
below the transition speed (0.8 f / 0.1 m/s) is a damper far too stiff for an explicit 5 ms step
on a foot.

The obstacles are spheres fixed to the ground, each with a force element of its own against the
four foot spheres, as the 2017 env made them: both surfaces of stiffness 10^6 / the obstacle's
radius, dissipation 1e-5 s/m, no friction. Sphere on sphere, d is the overlap of the two along
the line between their centres, R = r1 r2 / (r1 + r2), and the force acts along that line at
the middle of the overlap: an elastic, frictionless push that a foot slides off. (MuJoCo's soft
contact, which the port used before, let a foot stand on an obstacle with the ground's
friction.) Its dissipation is too small for a force to turn negative, so the element's early
end above never happens there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from l2r.sim.opensim import Osim


OBSTACLE_STIFFNESS_TIMES_RADIUS = 1e6  # N/m: an obstacle's stiffness (N/m^2) is this over its radius
OBSTACLE_DISSIPATION = 1e-5  # s/m


@dataclass(frozen=True)
class ContactLaw:
    stiffness: float  # N/m^2, the .osim's value (OpenSim hands Simbody stiffness^(2/3))
    dissipation: float  # s/m
    static_friction: float
    dynamic_friction: float
    viscous_friction: float  # s/m
    transition_velocity: float  # m/s

    def scaled(self, stiffness: float, dissipation: float, friction: float) -> ContactLaw:
        """This law with its stiffness, dissipation and friction coefficients (static, dynamic and
        viscous together) scaled by these factors."""
        return ContactLaw(self.stiffness * stiffness, self.dissipation * dissipation, self.static_friction * friction,
                          self.dynamic_friction * friction, self.viscous_friction * friction,
                          self.transition_velocity)

    def table(self) -> np.ndarray:
        """The kernel's parameters: [k, c, μs, μd, μv, v_transition], k the Hertz constant."""
        k = self.stiffness ** (2.0 / 3.0) / 2.0
        return np.array([k, self.dissipation, self.static_friction, self.dynamic_friction,
                         self.viscous_friction, self.transition_velocity])


def contact_elements(osim: Osim, spheres: tuple[str, ...]) -> np.ndarray:
    """Each sphere's Hunt-Crossley force element in the .osim, numbered (`ground_forces`' element)."""
    names = sorted({osim.contact_elements[s] for s in spheres})
    return np.array([names.index(osim.contact_elements[s]) for s in spheres])


def contact_law(osim: Osim) -> ContactLaw:
    c = osim.contact
    return ContactLaw(c["stiffness"], c["dissipation"], c["static_friction"], c["dynamic_friction"],
                      c["viscous_friction"], c["transition_velocity"])


@numba.njit(cache=True, error_model="numpy")
def _friction(f: float, slip: float, law: np.ndarray) -> tuple[float, float]:
    """Friction magnitude against a slip speed, and its derivative with respect to that speed."""
    us, ud, uv, vt = law[2], law[3], law[4], law[5]
    s = slip / vt
    shape = ud + 2.0 * (us - ud) / (1.0 + s * s)
    dshape = -4.0 * (us - ud) * s / ((1.0 + s * s) ** 2) / vt
    if s < 1.0:
        return f * (s * shape + uv * slip), f * (shape / vt + s * dshape + uv)
    return f * (shape + uv * slip), f * (dshape + uv)


@numba.njit(cache=True)
def _point_velocity(cvel: np.ndarray, root_com: np.ndarray, px: float, py: float,
                    pz: float) -> tuple[float, float, float]:
    """The velocity of a body's material point at (px, py, pz) in the world: cvel is the body's
    (angular, linear) velocity at its root's subtree centre of mass, `root_com`."""
    rx, ry, rz = px - root_com[0], py - root_com[1], pz - root_com[2]
    return (cvel[3] + cvel[1] * rz - cvel[2] * ry, cvel[4] + cvel[2] * rx - cvel[0] * rz,
            cvel[5] + cvel[0] * ry - cvel[1] * rx)


@numba.njit(cache=True, error_model="numpy")
def ground_forces(law: np.ndarray, radius: np.ndarray, sphere: np.ndarray, body: np.ndarray,
                  root: np.ndarray, element: np.ndarray, geom_xpos: np.ndarray, xpos: np.ndarray, xmat: np.ndarray,
                  cvel: np.ndarray, subtree_com: np.ndarray, point: np.ndarray, local: np.ndarray,
                  force: np.ndarray, damping: np.ndarray) -> None:
    """Hunt-Crossley forces of spheres on the ground plane y = 0.

    radius (n,); sphere (n,) the spheres' geoms; body (n,) their bodies, root (n,) those bodies'
    roots; element (n,) their force elements (see the module text); geom_xpos, xpos, xmat, cvel,
    subtree_com: MuJoCo's arrays. Writes the contact points in world (`point`, n x 3) and in their
    body's frame (`local`), the force on each sphere (`force`, n x 2: x, y) and d force / d speed of
    the contact point along x and y (`damping`, n x 2, never positive: only dampers go to the
    implicit integrator).
    """
    k, c = law[0], law[1]
    cut = np.zeros(radius.shape[0], np.bool_)  # in contact, with no force: Simbody's loop ends there
    for i in range(radius.shape[0]):
        centre = geom_xpos[sphere[i]]
        depth = radius[i] - centre[1]
        b = body[i]
        point[i, 0] = centre[0]
        point[i, 1] = -0.5 * depth if depth > 0.0 else centre[1] - radius[i]
        point[i, 2] = centre[2]
        for j in range(3):
            local[i, j] = 0.0
            for r in range(3):  # xmat is row-major body-to-world: local = R^T (p - x)
                local[i, j] += xmat[b, 3 * r + j] * (point[i, r] - xpos[b, r])
        force[i, 0] = force[i, 1] = damping[i, 0] = damping[i, 1] = 0.0
        if depth <= 0.0:
            continue
        vx, vy, _ = _point_velocity(cvel[b], subtree_com[root[i]], point[i, 0], point[i, 1], point[i, 2])
        hertz = 4.0 / 3.0 * k * depth * np.sqrt(radius[i] * k * depth)
        f = hertz * (1.0 - 1.5 * c * vy)  # penetration rate is -vy
        if f <= 0.0:
            cut[i] = True  # leaving faster than the dissipation allows: no force at all
            continue
        force[i, 1] = f
        damping[i, 1] = -1.5 * c * hertz
        magnitude, slope = _friction(f, abs(vx), law)
        force[i, 0] = -magnitude if vx > 0.0 else magnitude
        damping[i, 0] = min(-slope, 0.0)
    for i in range(radius.shape[0]):
        for j in range(radius.shape[0]):
            if cut[j] and listed_before(j, i, element, radius, geom_xpos[sphere[j], 0], geom_xpos[sphere[i], 0]):
                force[i, 0] = force[i, 1] = damping[i, 0] = damping[i, 1] = 0.0


@numba.njit(cache=True)
def listed_before(j: int, i: int, element: np.ndarray, radius: np.ndarray, xj: float, xi: float) -> bool:
    """Whether Simbody lists sphere j's contact before sphere i's in one force element: the sweep
    along x orders them by their rearmost points (x - radius)."""
    return j != i and element[j] == element[i] and xj - radius[j] < xi - radius[i]


@numba.njit(cache=True, error_model="numpy")
def obstacle_forces(course: np.ndarray, radius: np.ndarray, sphere: np.ndarray, body: np.ndarray,
                    root: np.ndarray, geom_xpos: np.ndarray, xipos: np.ndarray, cvel: np.ndarray,
                    subtree_com: np.ndarray, force: np.ndarray, xfrc_applied: np.ndarray) -> None:
    """Hunt-Crossley forces of the obstacles on the foot spheres (see the module text).

    course (m, 3): each obstacle's centre x, y (z = 0) and radius, radius 0 for none; radius,
    sphere, body, root: the foot spheres' as in `ground_forces`, each sphere alone on its body.
    Writes the force on each sphere (`force`, n x 3) and sets it, with its moment about the
    body's centre of mass, as MuJoCo's `xfrc_applied` of the sphere's body.
    """
    for i in range(radius.shape[0]):
        b = body[i]
        force[i, :] = 0.0
        xfrc_applied[b, :] = 0.0
        centre = geom_xpos[sphere[i]]
        for o in range(course.shape[0]):
            r = course[o, 2]
            if r <= 0.0:
                continue
            nx, ny, nz = centre[0] - course[o, 0], centre[1] - course[o, 1], centre[2]
            gap = np.sqrt(nx * nx + ny * ny + nz * nz)
            depth = radius[i] + r - gap
            if depth <= 0.0 or gap == 0.0:
                continue
            nx, ny, nz = nx / gap, ny / gap, nz / gap  # from the obstacle's centre to the sphere's
            reach = r - 0.5 * depth
            px, py, pz = course[o, 0] + reach * nx, course[o, 1] + reach * ny, reach * nz
            vx, vy, vz = _point_velocity(cvel[b], subtree_com[root[i]], px, py, pz)
            k = (OBSTACLE_STIFFNESS_TIMES_RADIUS / r) ** (2.0 / 3.0) / 2.0
            hertz = 4.0 / 3.0 * k * depth * np.sqrt(radius[i] * r / (radius[i] + r) * k * depth)
            f = hertz * (1.0 - 1.5 * OBSTACLE_DISSIPATION * (vx * nx + vy * ny + vz * nz))
            if f <= 0.0:
                continue
            fx, fy, fz = f * nx, f * ny, f * nz
            force[i, 0] += fx
            force[i, 1] += fy
            force[i, 2] += fz
            ax, ay, az = px - xipos[b, 0], py - xipos[b, 1], pz - xipos[b, 2]
            xfrc_applied[b, 0] += fx
            xfrc_applied[b, 1] += fy
            xfrc_applied[b, 2] += fz
            xfrc_applied[b, 3] += ay * fz - az * fy
            xfrc_applied[b, 4] += az * fx - ax * fz
            xfrc_applied[b, 5] += ax * fy - ay * fx

"""`l2r.sim.contact`'s Hunt-Crossley feet, on the ground and on the obstacles, as Warp functions
over many worlds, in float32.

The law's table is the numba module's (`ContactLaw.table`); MuJoCo Warp's arrays hold one row
per world.
"""

from __future__ import annotations

import warp as wp

from l2r.sim import contact

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})

OBSTACLE_STIFFNESS_TIMES_RADIUS = wp.constant(contact.OBSTACLE_STIFFNESS_TIMES_RADIUS)
OBSTACLE_DISSIPATION = wp.constant(contact.OBSTACLE_DISSIPATION)


@wp.func
def _friction(f: float, slip: float, law: wp.array(dtype=float)):
    """Friction magnitude against a slip speed, and its derivative with respect to that speed."""
    us = law[2]
    ud = law[3]
    uv = law[4]
    vt = law[5]
    s = slip / vt
    shape = ud + 2.0 * (us - ud) / (1.0 + s * s)
    dshape = -4.0 * (us - ud) * s / ((1.0 + s * s) * (1.0 + s * s)) / vt
    if s < 1.0:
        return f * (s * shape + uv * slip), f * (shape / vt + s * dshape + uv)
    return f * (shape + uv * slip), f * (dshape + uv)


@wp.func
def _normal(law: wp.array(dtype=float), radius: float, centre: wp.vec3, cvel: wp.spatial_vector, root_com: wp.vec3):
    """One sphere on the ground plane y = 0: its depth, its contact point, the velocity of its
    body's material point there (cvel is (angular, linear) at the root's subtree com), the Hertz
    force and the normal force before it is clamped at 0."""
    k = law[0]
    c = law[1]
    depth = radius - centre[1]
    py = centre[1] - radius
    if depth > 0.0:
        py = -0.5 * depth
    point = wp.vec3(centre[0], py, centre[2])
    v = wp.spatial_bottom(cvel) + wp.cross(wp.spatial_top(cvel), point - root_com)
    hertz = 0.0
    if depth > 0.0:
        hertz = 4.0 / 3.0 * k * depth * wp.sqrt(radius * k * depth)
    return depth, point, v, hertz, hertz * (1.0 - 1.5 * c * v[1])  # penetration rate is -vy


@wp.func
def sphere_force(law: wp.array(dtype=float), radius: float, centre: wp.vec3, body_pos: wp.vec3, body_mat: wp.mat33,
                 cvel: wp.spatial_vector, root_com: wp.vec3):
    """One sphere on the ground plane y = 0: the contact point in the world and in its body, the
    force (x, y) and d force / d speed of the point along x and y (never positive)."""
    depth, point, v, hertz, f = _normal(law, radius, centre, cvel, root_com)
    local = wp.transpose(body_mat) * (point - body_pos)  # xmat is body-to-world
    force = wp.vec2(0.0, 0.0)
    damping = wp.vec2(0.0, 0.0)
    if depth > 0.0 and f > 0.0:  # otherwise off the ground, or leaving faster than the dissipation allows
        magnitude, slope = _friction(f, wp.abs(v[0]), law)
        fx = magnitude
        if v[0] > 0.0:
            fx = -magnitude
        force = wp.vec2(fx, f)
        damping = wp.vec2(wp.min(-slope, 0.0), -1.5 * law[1] * hertz)
    return point, local, force, damping


@wp.func
def foot_force(law: wp.array(dtype=float), radius: wp.array(dtype=float), sphere: wp.array(dtype=int),
               body: wp.array(dtype=int), root: wp.array(dtype=int), element: wp.array(dtype=int), w: int, i: int,
               geom_xpos: wp.array2d(dtype=wp.vec3), xpos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33),
               cvel: wp.array2d(dtype=wp.spatial_vector), subtree_com: wp.array2d(dtype=wp.vec3)):
    """`sphere_force` of world w's sphere i, with none where a sphere listed before it in its force
    element is in contact with no force (`contact.ground_forces`: Simbody's loop ends there)."""
    b = body[i]
    centre = geom_xpos[w, sphere[i]]
    point, local, force, damping = sphere_force(law, radius[i], centre, xpos[w, b], xmat[w, b], cvel[w, b],
                                                subtree_com[w, root[i]])
    for j in range(radius.shape[0]):
        other = geom_xpos[w, sphere[j]]
        if j != i and element[j] == element[i] and other[0] - radius[j] < centre[0] - radius[i]:
            depth, p, v, hertz, f = _normal(law, radius[j], other, cvel[w, body[j]], subtree_com[w, root[j]])
            if depth > 0.0 and f <= 0.0:
                force = wp.vec2(0.0, 0.0)
                damping = wp.vec2(0.0, 0.0)
    return point, local, force, damping


@wp.kernel
def ground_forces(law: wp.array(dtype=float), radius: wp.array(dtype=float), sphere: wp.array(dtype=int),
                  body: wp.array(dtype=int), root: wp.array(dtype=int), element: wp.array(dtype=int),
                  geom_xpos: wp.array2d(dtype=wp.vec3), xpos: wp.array2d(dtype=wp.vec3),
                  xmat: wp.array2d(dtype=wp.mat33), cvel: wp.array2d(dtype=wp.spatial_vector),
                  subtree_com: wp.array2d(dtype=wp.vec3), point: wp.array2d(dtype=wp.vec3),
                  local: wp.array2d(dtype=wp.vec3), force: wp.array2d(dtype=wp.vec2),
                  damping: wp.array2d(dtype=wp.vec2)):
    """`contact.ground_forces`, one thread per world and sphere."""
    w, i = wp.tid()
    p, q, f, c = foot_force(law, radius, sphere, body, root, element, w, i, geom_xpos, xpos, xmat, cvel, subtree_com)
    point[w, i] = p
    local[w, i] = q
    force[w, i] = f
    damping[w, i] = c


@wp.func
def obstacle_push(course: wp.array(dtype=wp.vec3), radius: float, centre: wp.vec3, body_com: wp.vec3,
                  cvel: wp.spatial_vector, root_com: wp.vec3):
    """`contact.obstacle_forces` for one foot sphere: the force of the obstacles (x, y, radius;
    centres at z = 0) on it and that force's moment about its body's centre of mass."""
    force = wp.vec3(0.0, 0.0, 0.0)
    moment = wp.vec3(0.0, 0.0, 0.0)
    for o in range(course.shape[0]):
        r = course[o][2]
        if r > 0.0:
            normal = centre - wp.vec3(course[o][0], course[o][1], 0.0)
            gap = wp.length(normal)
            depth = radius + r - gap
            if depth > 0.0 and gap > 0.0:
                normal = normal / gap  # from the obstacle's centre to the sphere's
                point = wp.vec3(course[o][0], course[o][1], 0.0) + (r - 0.5 * depth) * normal
                v = wp.spatial_bottom(cvel) + wp.cross(wp.spatial_top(cvel), point - root_com)
                k = wp.pow(OBSTACLE_STIFFNESS_TIMES_RADIUS / r, 2.0 / 3.0) / 2.0
                hertz = 4.0 / 3.0 * k * depth * wp.sqrt(radius * r / (radius + r) * k * depth)
                f = hertz * (1.0 - 1.5 * OBSTACLE_DISSIPATION * wp.dot(v, normal))
                if f > 0.0:
                    force += f * normal
                    moment += wp.cross(point - body_com, f * normal)
    return force, moment

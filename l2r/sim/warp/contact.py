"""`l2r.sim.contact`'s Hunt-Crossley feet as a Warp kernel over many worlds, in float32.

The law's table is the numba module's (`ContactLaw.table`); MuJoCo Warp's arrays hold one row
per world.
"""

from __future__ import annotations

import warp as wp

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})


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
def sphere_force(law: wp.array(dtype=float), radius: float, centre: wp.vec3, body_pos: wp.vec3, body_mat: wp.mat33,
                 cvel: wp.spatial_vector, root_com: wp.vec3):
    """One sphere on the ground plane y = 0: the contact point in the world and in its body, the
    force (x, y) and d force / d speed of the point along x and y (never positive)."""
    k = law[0]
    c = law[1]
    depth = radius - centre[1]
    py = centre[1] - radius
    if depth > 0.0:
        py = -0.5 * depth
    point = wp.vec3(centre[0], py, centre[2])
    local = wp.transpose(body_mat) * (point - body_pos)  # xmat is body-to-world
    force = wp.vec2(0.0, 0.0)
    damping = wp.vec2(0.0, 0.0)
    if depth > 0.0:
        # the body's material point at the contact: cvel is (angular, linear) at the root's subtree com
        r = point - root_com
        w = wp.spatial_top(cvel)
        v = wp.spatial_bottom(cvel) + wp.cross(w, r)
        hertz = 4.0 / 3.0 * k * depth * wp.sqrt(radius * k * depth)
        f = hertz * (1.0 - 1.5 * c * v[1])  # penetration rate is -vy
        if f > 0.0:  # otherwise leaving faster than the dissipation allows: no force at all
            magnitude, slope = _friction(f, wp.abs(v[0]), law)
            fx = magnitude
            if v[0] > 0.0:
                fx = -magnitude
            force = wp.vec2(fx, f)
            damping = wp.vec2(wp.min(-slope, 0.0), -1.5 * c * hertz)
    return point, local, force, damping


@wp.kernel
def ground_forces(law: wp.array(dtype=float), radius: wp.array(dtype=float), sphere: wp.array(dtype=int),
                  body: wp.array(dtype=int), root: wp.array(dtype=int), geom_xpos: wp.array2d(dtype=wp.vec3),
                  xpos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33),
                  cvel: wp.array2d(dtype=wp.spatial_vector), subtree_com: wp.array2d(dtype=wp.vec3),
                  point: wp.array2d(dtype=wp.vec3), local: wp.array2d(dtype=wp.vec3),
                  force: wp.array2d(dtype=wp.vec2), damping: wp.array2d(dtype=wp.vec2)):
    """`contact.ground_forces`, one thread per world and sphere."""
    w, i = wp.tid()
    b = body[i]
    p, q, f, c = sphere_force(law, radius[i], geom_xpos[w, sphere[i]], xpos[w, b], xmat[w, b], cvel[w, b],
                              subtree_com[w, root[i]])
    point[w, i] = p
    local[w, i] = q
    force[w, i] = f
    damping[w, i] = c

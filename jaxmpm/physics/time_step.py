"""The time step: the one policy that sets it from the CFL condition, and every check of it.

The explicit step is stable while no wave and no body crosses a cell in one step:
    dt <= h / max over bodies of s_b,
s_b = c_p + |v0| for a free body (its p-wave speed from its material, plus its speed), and
the speed alone for a prescribed, rigid or subcycled body (their stiffness never sets the step).
A scene runs at dt = cfl * that limit, or at its own `scene.dt`, trimmed down so that a whole
number of steps fills each output interval (`time_stepping`); a subcycled body takes n steps
of dt / n within it, n given or the fewest with dt / n <= cfl h / s_b (`substeps`). The step is then fixed: parameter
values given later (calibration, `--set` on a compiled simulation, initial velocities) are
checked against it (`material_limits`, `exceeds`), never used to change it.
"""

from __future__ import annotations

import math

from jaxmpm.errors import SceneError
from jaxmpm.materials.base import material_parameters

STEP_SLACK = 1e-6   # relative round-off allowed between a time step and its stable limit


def body_speed(scene, body, params=None, initial_speed=None) -> float:
    """s_b for one body [m/s]: c_p (from `params` of its material, default the scene's values)
    + its initial speed for a free body; its initial or prescribed speed alone for a rigid or
    prescribed one."""
    motion = math.hypot(*body.velocity) if initial_speed is None else initial_speed
    if body.kinematics.type == "prescribed":
        return body.kinematics.top_speed
    if body.kinematics.type == "rigid":
        return motion
    return own_speed(scene, body, params, motion)


def own_speed(scene, body, params=None, motion=None) -> float:
    """c_p + |v| of a free body, subcycled or not [m/s] (`body_speed`)."""
    material = scene.material_of(body)
    values = material_parameters(material) if params is None else params
    motion = math.hypot(*body.velocity) if motion is None else motion
    return float(material.wave_speed(values)) + motion


def stable_limit(scene) -> float:
    """h / max over bodies of s_b [s] (inf when nothing moves or carries waves); a subcycled
    body counts with its speed alone."""
    speed = max(math.hypot(*body.velocity) if body.kinematics.subcycled else body_speed(scene, body)
                for body in scene.bodies)
    return scene.grid.cell / speed if speed > 0.0 else math.inf


def substeps(scene, body, dt) -> int:
    """The steps a body takes within each scene step dt: 1 unless subcycled; its given n, or
    for "auto" the fewest with dt / n <= cfl * h / (c_p + |v|). SceneError if a given n
    leaves its substep above its stable limit."""
    if not body.kinematics.subcycled:
        return 1
    limit = scene.grid.cell / own_speed(scene, body)
    if body.kinematics.substeps == "auto":
        return max(1, math.ceil(dt / (scene.cfl * limit) * (1.0 - STEP_SLACK)))
    count = int(body.kinematics.substeps)
    if exceeds(dt / count, limit):
        raise SceneError(
            f"body {body.name!r}: kinematics.substeps = {count} leaves its step {dt / count:.4g} s above its stable "
            f"limit {limit:.4g} s (cell / its p-wave speed): give at least {math.ceil(dt / limit)}, or 'auto'."
        )
    return count


def exceeds(dt: float, limit: float) -> bool:
    """Whether dt is above a stable limit beyond round-off (STEP_SLACK)."""
    return dt > limit * (1.0 + STEP_SLACK)


def check_scene_step(scene):
    """SceneError if the scene's own `dt` is above its stable limit."""
    limit = stable_limit(scene)
    if scene.dt is not None and scene.dt > limit:
        raise SceneError(
            f"scene.dt = {scene.dt:g} s is above the stable limit {limit:.4g} s "
            "(cell / max wave speed): use a smaller dt, or give cfl instead."
        )


def time_stepping(scene):
    """(dt, steps per output, outputs): dt <= cfl * stable limit (or <= scene.dt), adjusted
    down so that a whole number of steps fills each output interval; the duration is rounded
    to a whole number of output intervals."""
    largest = scene.dt if scene.dt is not None else scene.cfl * stable_limit(scene)
    if not math.isfinite(largest):
        raise SceneError(
            "scene.cfl cannot set the time step: no body is free and none moves. Give scene.dt instead."
        )
    interval = scene.output_interval
    per_output = max(1, math.ceil(interval / largest - 1e-9))
    outputs = max(1, round(scene.duration / interval))
    if abs(outputs * interval - scene.duration) > 1e-6 * scene.duration:
        outputs = math.ceil(scene.duration / interval)
    return interval / per_output, per_output, outputs


def material_limits(scene, materials, body_speeds=None) -> dict:
    """{material: h / (c_p + speed of its fastest free body), times n for a body subcycled n
    times} for parameter values `materials` ({material: {name: value}}) [s]; a body's speed is
    its scene velocity, or body_speeds[body name] when given (e.g. the largest |v| of its
    points in a state)."""
    limits = {}
    dt = time_stepping(scene)[0] if any(body.kinematics.subcycled for body in scene.bodies) else None
    for body in scene.bodies:
        if body.kinematics.type != "free":
            continue
        moving = None if body_speeds is None else body_speeds.get(body.name)
        limit = scene.grid.cell / body_speed(scene, body, materials[body.material], moving)
        if body.kinematics.subcycled:     # its steps are dt / n
            limit = limit * substeps(scene, body, dt)
        limits[body.material] = min(limit, limits.get(body.material, limit))
    return limits

"""The weights scene's model: the pickplace scene without its wall and target, with a wrist force/torque site and
sensors, coupled fingers, the pick spot and the four zones."""

from __future__ import annotations

import mujoco

from lerobot_cnmp.sims.pickplace.model import MJCF as PICKPLACE_MJCF
from lerobot_cnmp.sims.pickplace.model import lookat_xyaxes
from lerobot_cnmp.sims.weights.task import PICK_XY, ZONE_HALF, ZONE_RGBA, ZONE_XY

CAMERA_EYE = (1.95, -1.15, 1.25)
CAMERA_TARGET = (0.55, 0.05, 0.22)


def build_model() -> mujoco.MjModel:
    """The pickplace scene without its wall and target, with the F/T site and sensors, coupled fingers and the
    four zones."""
    spec = mujoco.MjSpec.from_string(PICKPLACE_MJCF)
    spec.modelname = "cnmp_weights_ur10"
    spec.delete(spec.geom("wall"))
    spec.delete(spec.site("target"))
    spec.delete(spec.site("pick"))
    spec.body("gripper").add_site(name="ft", pos=[0.0, 0.0, 0.0], size=[0.008, 0.0, 0.0], rgba=[0.9, 0.1, 0.1, 0.6])
    for name, kind in (("ft_force", mujoco.mjtSensor.mjSENS_FORCE), ("ft_torque", mujoco.mjtSensor.mjSENS_TORQUE)):
        spec.add_sensor(name=name, type=kind, objtype=mujoco.mjtObj.mjOBJ_SITE, objname="ft")
    # a parallel gripper: the right finger follows the left one (polynomial q_r = q_l)
    coupling = spec.add_equality(type=mujoco.mjtEq.mjEQ_JOINT, name1="finger_left", name2="finger_right")
    coupling.data[:5] = [0.0, 1.0, 0.0, 0.0, 0.0]
    world = spec.worldbody
    world.add_site(name="pick", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[*PICK_XY, 0.0004], size=[0.04, 0.04, 0.0004],
                   rgba=[0.3, 0.3, 0.9, 0.4])
    for z, (xy, rgba) in enumerate(zip(ZONE_XY, ZONE_RGBA, strict=True)):
        world.add_site(name=f"zone{z}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[*xy, 0.0005],
                       size=[ZONE_HALF, ZONE_HALF, 0.0005], rgba=list(rgba))
    cam = spec.camera("scene")
    cam.pos = list(CAMERA_EYE)
    cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    cam.alt.xyaxes = [float(v) for v in lookat_xyaxes(CAMERA_EYE, CAMERA_TARGET).split()]
    return spec.compile()

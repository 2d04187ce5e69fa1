"""One control step of the arm's joint servos (shared by the arm sims)."""

from __future__ import annotations

import mujoco
import numpy as np

from lerobot_cnmp.sims.pickplace.model import ARM_POS_CTRL, ARM_VEL_CTRL, JOINT_SPEED_LIMITS, N_SUBSTEPS


def servo_control_step(model, data, prev_command, joint_command, on_substep=None) -> np.ndarray:
    """One 50 Hz control step of the arm's joint servos; returns the joint target reached (the new command).

    First-order hold: the joint targets ramp from ``prev_command`` to ``joint_command`` over the control
    step, with the ramp's velocity fed forward (like a robot controller interpolating servo targets). The
    controller limits the joint speed to the UR10's. The finger ``ctrl`` entries are left as they are.
    ``on_substep()`` is called after each of the ``N_SUBSTEPS`` physics steps.
    """
    d = data
    prev = np.asarray(prev_command, dtype=np.float64)
    max_delta = JOINT_SPEED_LIMITS * (N_SUBSTEPS * model.opt.timestep)
    target = prev + np.clip(np.asarray(joint_command, dtype=np.float64) - prev, -max_delta, max_delta)
    d.ctrl[ARM_VEL_CTRL] = (target - prev) / (N_SUBSTEPS * model.opt.timestep)
    for i in range(N_SUBSTEPS):
        # semi-implicit Euler moves the joint with the updated velocity, so substep i servos to the
        # ramp at its start; the joints reach ``target`` at the end of the control step
        d.ctrl[ARM_POS_CTRL] = prev + (target - prev) * (i / N_SUBSTEPS)
        mujoco.mj_step(model, d)
        if on_substep is not None:
            on_substep()
    d.ctrl[ARM_POS_CTRL] = target
    return target

"""The point-mass MJCF that the obstacle2d and room sims share: a sphere on two slide joints (x, y) driven by
critically damped position servos, no gravity, a 2 ms implicit-fast physics step, a checkered floor texture,
hidden marker sites for the conditions, and the sim's own scene (cameras, floor, obstacles, goal marker)."""

from __future__ import annotations

import numpy as np


def critical_damping(kp: float, mass: float = 1.0) -> float:
    """The servo damping ``2 sqrt(kp m)`` that makes a position servo on mass ``m`` critically damped."""
    return 2.0 * np.sqrt(kp * mass)


def point_mass_mjcf(
    name: str,
    *,
    scene: str,
    agent_radius: float,
    agent_attrs: str,
    kp: float,
    ctrl_low,
    ctrl_high,
    n_condition_sites: int,
    condition_site_half: float,
    offscreen_size: int = 1024,
    headlight: str = 'ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5"',
) -> str:
    """The MJCF of a point-mass sim.

    Args:
        name: the model's name.
        scene: worldbody XML placed before the agent (cameras, floor, walls, obstacles).
        agent_radius: radius of the agent's sphere (mass 1).
        agent_attrs: extra attributes of the agent's geom (colour, collision or visual groups).
        kp: position gain of the two servos (their damping is critical for mass 1).
        ctrl_low, ctrl_high: the servos' (x, y) control ranges.
        n_condition_sites: marker sites ``cond0..`` (hidden until an episode places them).
        condition_site_half: half side of a condition marker.
        offscreen_size: side of the offscreen render buffer, pixels.
        headlight: attributes of the headlight.
    """
    kv = critical_damping(kp)
    h = condition_site_half
    sites = "\n".join(
        f'    <site name="cond{k}" type="box" pos="0 0 0.07" size="{h} {h} 0.002" rgba="0 0 0 0"/>'
        for k in range(n_condition_sites)
    )
    servos = "\n".join(
        f'    <position name="a{axis}" joint="{axis}" kp="{kp}" kv="{kv}" ctrllimited="true"\n'
        f'              ctrlrange="{ctrl_low[i]} {ctrl_high[i]}"/>'
        for i, axis in enumerate("xy")
    )
    return f"""
<mujoco model="{name}">
  <option timestep="0.002" gravity="0 0 0" integrator="implicitfast"/>
  <visual>
    <global offwidth="{offscreen_size}" offheight="{offscreen_size}"/>
    <headlight {headlight}/>
  </visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.92 0.92 0.92" rgb2="0.85 0.85 0.85"
             width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
  <worldbody>
{scene}
    <body name="agent" pos="0 0 0">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom name="agent" type="sphere" size="{agent_radius}" mass="1" {agent_attrs}/>
    </body>
{sites}
  </worldbody>
  <actuator>
{servos}
  </actuator>
</mujoco>
"""

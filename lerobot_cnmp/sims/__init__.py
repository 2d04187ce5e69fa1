"""CNMP sims: gymnasium registration, LeRobot env configs and the recorder's sim registry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import gymnasium as gym

from lerobot_cnmp.sims.pickplace import env as pickplace
from lerobot_cnmp.sims.room import env as room
from lerobot_cnmp.sims.weights import env as weights
from lerobot_cnmp.sims.configs import (
    OBSTACLE2D_GYM_ID,
    PICKPLACE_GYM_ID,
    ROOM_GYM_ID,
    WEIGHTS_GYM_ID,
    CNMPObstacle2DEnv,
    CNMPPickPlaceEnv,
    CNMPRoomEnv,
    CNMPWeightsEnv,
    CNMPMetaWorldEnv,
    METAWORLD_GYM_ID,
)
from lerobot_cnmp.sims.obstacle2d.env import DEFAULT_MAX_EPISODE_STEPS, ENV_STATE_DIM, MAX_CONDITIONS
from lerobot_cnmp.sims.so101 import env as so101  # registers cnmp_so101 and cnmp/SO101PickPlace-v0

for _gym_id, _entry_point, _max_steps in (
    (OBSTACLE2D_GYM_ID, "lerobot_cnmp.sims.obstacle2d.env:Obstacle2DEnv", DEFAULT_MAX_EPISODE_STEPS),
    (PICKPLACE_GYM_ID, "lerobot_cnmp.sims.pickplace.env:PickPlaceEnv", pickplace.DEFAULT_MAX_EPISODE_STEPS),
    (WEIGHTS_GYM_ID, "lerobot_cnmp.sims.weights.env:WeightsEnv", weights.DEFAULT_MAX_EPISODE_STEPS),
    (ROOM_GYM_ID, "lerobot_cnmp.sims.room.env:RoomEnv", room.DEFAULT_MAX_EPISODE_STEPS),
    (METAWORLD_GYM_ID, "lerobot_cnmp.sims.metaworld.env:MetaWorldEnv", 500),
):
    if _gym_id not in gym.registry:
        gym.register(id=_gym_id, entry_point=_entry_point, max_episode_steps=_max_steps)


def _condition_names(max_conditions: int, sm_names: list[str]) -> list[str]:
    names = []
    for k in range(max_conditions):
        names += [f"c{k}_present", f"c{k}_phase"]
        names += [f"c{k}_{n}" for n in sm_names]
        names += [f"c{k}_mask_{n}" for n in sm_names]
    return names


@dataclass(frozen=True)
class SimSpec:
    """What the generic recorder (``lerobot_cnmp.record``) needs to know about a sim.

    Attributes:
        env_config_cls: the LeRobot ``EnvConfig`` subclass that builds the env.
        expert_cls: scripted demonstrator, ``expert_cls(env.unwrapped)`` with ``reset()`` and ``act(step)``.
        demo_length: frames per demonstration.
        default_episodes: episodes recorded when none are asked for.
        default_conditions: the config's ``conditions`` used when recording.
        feature_names: per env-observation key (and ``action``), the names of the vector's entries.
        reset_options: ``(i, conditions) -> options`` passed to ``reset`` for episode ``i`` recorded with
            the config's ``conditions`` (e.g. to balance modes).
        episode_label: ``env.unwrapped -> str`` label of the recorded episode for the dataset card.
        description: markdown paragraph about the sim for the dataset card.
        features_note: markdown paragraph about the recorded features for the dataset card.
        config_kwargs: ``conditions -> kwargs`` of ``env_config_cls`` for recording with those conditions.
    """

    env_config_cls: type
    expert_cls: type
    demo_length: int
    default_episodes: int
    default_conditions: str
    feature_names: dict[str, list[str]] = field(default_factory=dict)
    reset_options: Callable[[int, str], dict[str, Any] | None] = lambda i, conditions: None
    episode_label: Callable[[Any], str] = lambda env: ""
    description: str = ""
    features_note: str = ""
    config_kwargs: Callable[[str], dict[str, Any]] = lambda conditions: {"conditions": conditions}


def _obstacle2d_reset_options(i: int, conditions: str) -> dict[str, Any] | None:
    # even episodes pass over the obstacle, odd ones under it: the demos are balanced between modes
    # (the paper_* condition sets fix the mode themselves)
    if conditions in ("random", "mixed"):
        return {"mode": 1 if i % 2 == 0 else -1}
    return None


def _obstacle2d_spec() -> SimSpec:
    from lerobot_cnmp.sims.obstacle2d.expert import Obstacle2DExpert

    return SimSpec(
        env_config_cls=CNMPObstacle2DEnv,
        expert_cls=Obstacle2DExpert,
        demo_length=200,
        default_episodes=64,
        default_conditions="random",
        feature_names={
            "action": ["x", "y"],
            "agent_pos": ["x", "y"],
            "environment_state": _condition_names(MAX_CONDITIONS, ["x", "y"]),
        },
        reset_options=_obstacle2d_reset_options,
        episode_label=lambda env: env.task.mode_name,
        features_note=(
            "`observation.environment_state` holds the episode's conditions, constant within an episode, in "
            "the layout of `lerobot_cnmp.execution.conditions` with SM dimension 2 and 4 slots: slot k is "
            "`[present, phase, x, y, mask_x, mask_y]` (unused slots all zeros; `mask` marks the constrained dims)."
        ),
        description=(
            "A MuJoCo point mass (sphere, radius 0.03, mass 1) moves in the plane under position control "
            "(two slide joints, critically damped position servos, 2 ms physics step, 10 physics steps "
            "per 50 Hz control step) from the left (x=0) to the right (x=1) of a round obstacle (centre "
            "(0.5, 0), radius 0.2), passing either over it (mode +1) or under it (mode -1), as in the 2D "
            "obstacle-avoidance experiment of Seker et al. (RSS 2019, Sec. IV-A). Each episode follows a "
            "hidden reference of the family x(tau) = tau, y(tau) = y0 + (h - y0) sin(pi tau)^p, "
            "tau in [0, 1], with y0 in s[0.1, 0.3], h in s[0.45, 0.65], p in [0.9, 1.6] for mode s; the "
            "start is (0, y0) and the goal (1, y0). A scripted expert commands the reference position at "
            "each step's phase (tau_k = k/199); the recorded positions are those the simulated "
            "servo reached, not the formula."
        ),
    )


def _obstacle2d_shared_spec() -> SimSpec:
    """The obstacle sim's ``shared`` family (both modes share the start and the goal): same expert, features
    and balanced modes as ``cnmp_obstacle2d``; the env config gets ``family="shared"``."""
    import dataclasses

    base = _obstacle2d_spec()
    return dataclasses.replace(
        base,
        config_kwargs=lambda conditions: {"conditions": conditions, "family": "shared"},
        description=base.description.replace(
            "with y0 in s[0.1, 0.3], h in s[0.45, 0.65], p in [0.9, 1.6] for mode s; the start is (0, y0) and "
            "the goal (1, y0).",
            "with y0 in [-0.1, 0.1] for both modes (family `shared`: the two modes share the start (0, y0) and "
            "the goal (1, y0), the paper's setting), h in s[0.45, 0.65], p in [0.9, 1.6] for mode s.")
        + " Record and evaluate with `--env.family=shared`.",
    )


def _pickplace_reset_options(i: int, conditions: str) -> dict[str, Any]:
    # the paper's 8 training demos: object {2, 6} cm x obstacle {2, 4, 6, 8} cm, in turn
    grid = pickplace.PAPER_TRAIN_GRID
    return {"task_params": grid[i % len(grid)]}


def _records_only(sim: str, conditions_name: str, what: str) -> Callable[[str], dict[str, Any]]:
    """``config_kwargs`` of a sim that records one fixed set of episodes (its ``reset_options``): the only
    valid ``conditions`` is that set's name, and the env config takes no conditions option."""

    def config_kwargs(conditions: str) -> dict[str, Any]:
        if conditions != conditions_name:
            raise ValueError(f"{sim} records {what} only (conditions {conditions_name!r}), got {conditions!r}")
        return {}

    return config_kwargs


def _pickplace_spec() -> SimSpec:
    from lerobot_cnmp.sims.pickplace.expert import PickPlaceExpert

    joints = [*pickplace.JOINT_NAMES, "gripper"]
    return SimSpec(
        env_config_cls=CNMPPickPlaceEnv,
        expert_cls=PickPlaceExpert,
        demo_length=pickplace.DEMO_LENGTH,
        default_episodes=len(pickplace.PAPER_TRAIN_GRID),
        default_conditions="grid",
        feature_names={"action": joints, "agent_pos": joints, "environment_state": ["object_cm", "obstacle_cm"]},
        reset_options=_pickplace_reset_options,
        episode_label=lambda env: "gamma=({:g}, {:g})".format(*env.task_params),
        features_note=(
            "`observation.task_params` holds gamma = (object height, obstacle height) in cm, constant within "
            "an episode; `observation.state` the measured joint angles (rad) and gripper closure in [0, 1]; "
            "`action` the commanded joint angles and gripper command."
        ),
        config_kwargs=_records_only("cnmp_pickplace", "grid", "the paper's gamma grid"),
        description=(
            "A MuJoCo arm with the UR10's published DH kinematics (6 position-servoed joints, gravity "
            "compensated, 50 Hz control) and a parallel two-finger gripper picks a 4 x 4 cm box of height "
            "gamma_object cm from (0.70, -0.25) and places it on a 10 x 10 cm target area at (0.70, 0.25), "
            "carrying it along an arc over a 2 cm thick wall of height gamma_obstacle cm standing between "
            "them, as in the pick-and-place experiment of Seker et al. (RSS 2019, Sec. IV-C). The grasp is "
            "physical (friction of the finger pads only). A scripted expert plans the tool point in "
            "Cartesian space (grasp height linear in the object height, arc apex with the object 5 cm "
            "above the wall top, fixed phase timing, minimum-jerk segments) and converts it to joint angles by damped-least-squares IK "
            "on MuJoCo Jacobians; the SM is the 6 joint angles (radians) plus the gripper command in [0, 1], "
            "and gamma is stored as observation.task_params (cm)."
        ),
    )


def _weights_demos() -> list[tuple[int, float]]:
    # the paper's 20 demos: 2 shapes x 2 weight categories x 5 masses
    return [(shape, m) for shape in range(len(weights.SHAPES)) for cat in weights.WEIGHT_CATEGORIES
            for m in weights.DEMO_MASSES[cat]]


def _weights_reset_options(i: int, conditions: str) -> dict[str, Any]:
    shape, mass = _weights_demos()[i % len(_weights_demos())]
    return {"shape": shape, "mass": mass}


def _weights_spec() -> SimSpec:
    from lerobot_cnmp.sims.weights.expert import WeightsExpert

    names = list(weights.SM_NAMES)
    return SimSpec(
        env_config_cls=CNMPWeightsEnv,
        expert_cls=WeightsExpert,
        demo_length=weights.DEMO_LENGTH,
        default_episodes=len(_weights_demos()),
        default_conditions="demo_masses",
        feature_names={"action": names, "agent_pos": names},
        reset_options=_weights_reset_options,
        episode_label=lambda env: f"{weights.SHAPES[env.shape][0]}, {env.mass:g} kg",
        config_kwargs=_records_only("cnmp_weights", "demo_masses", "its demo masses"),
        features_note=(
            "`observation.state` and `action` are the SM in task space: the tool point (x, y, z, m), the two "
            "finger joint positions (m) and the wrist force/torque reading (N, N·m, zeroed at reset, 100 ms "
            "low-pass). The env ignores the F/T entries of an action (forces cannot be commanded); the "
            "expert fills them with the previous reading. The container's class (shape, weight category) "
            "is in the episode labels above only, never in a feature."
        ),
        description=(
            "The UR10-like arm of cnmp_pickplace with a wrist force/torque sensor picks a container from the "
            "middle of the table, (0.70, -0.20), and places it on one of four 12 x 12 cm zones chosen by its "
            "shape (a 4 cm box or a 6 cm cube, which close the fingers to different widths) and its weight "
            "category (light 0.15-0.35 kg, heavy 0.65-0.95 kg), as in the sensorimotor classification "
            "experiment of Seker et al. (RSS 2019, Sec. IV-D). The arm is driven in task space: each step the "
            "tool-point target is converted to joints by IK. A scripted expert, who knows the class, plans "
            "approach, grasp, lift, carry, place and release with minimum-jerk segments; 5 masses per "
            "category and shape give the paper's 20 demonstrations."
        ),
    )


def _room_config_kwargs(conditions: str) -> dict[str, Any]:
    # the recorder's --conditions is the env's `condition` option (checked by CNMPRoomEnv)
    return {"condition": conditions}


def _room_spec() -> SimSpec:
    from lerobot_cnmp.sims.room.expert import RoomExpert

    return SimSpec(
        env_config_cls=CNMPRoomEnv,
        expert_cls=RoomExpert,
        demo_length=room.DEMO_LENGTH,
        default_episodes=1000,
        default_conditions="start_end",
        feature_names={
            "action": ["x", "y"],
            "agent_pos": ["x", "y"],
            "environment_state": _condition_names(room.MAX_CONDITIONS, ["x", "y"]),
        },
        episode_label=lambda env: env.task.layout,
        config_kwargs=_room_config_kwargs,
        features_note=(
            "`observation.images.top` is the room's top-down binary mask, "
            f"{room.DEFAULT_IMAGE_SIZE} x {room.DEFAULT_IMAGE_SIZE} RGB (the three channels equal), 255 on the "
            "obstacles and 0 on the free floor, constant within an episode and stored as PNG frames (dtype "
            "`image`, no video). Image row 0 is the top of the room (y = 1) and column 0 its left side "
            f"(x = 0): pixel (r, c) covers x = (c + 0.5) / {room.DEFAULT_IMAGE_SIZE}, y = 1 - (r + 0.5) / "
            f"{room.DEFAULT_IMAGE_SIZE} at its centre; the "
            "walls lie just outside the imaged square. `observation.environment_state` holds the episode's "
            "conditions, constant within an episode, in the layout of `lerobot_cnmp.execution.conditions` with SM "
            "dimension 2 and 3 slots: slot k is `[present, phase, x, y, mask_x, mask_y]` (unused slots all "
            "zeros)."
        ),
        description=(
            "A MuJoCo point mass (sphere, radius 0.02, mass 1; two slide joints with critically damped "
            "position servos, 2 ms physics step, 10 physics steps per 50 Hz control step) crosses a walled "
            "room, x, y in [0, 1], from left to right around two rectangular obstacles attached to opposite "
            "walls, as in the top-down image experiment of Seker et al. (RSS 2019, Sec. IV-B). Each episode "
            "draws a room: one obstacle centred at x in [0.25, 0.45] and one at x in [0.55, 0.75], one hanging "
            "from the bottom wall and the other from the top wall (which one at random: the episode label "
            "bottom-first / top-first names the wall of the left one), widths in [0.06, 0.14], lengths into the "
            "room in [0.35, 0.6]; a start at x in [0.05, 0.12] and an end at x in [0.88, 0.95], y in "
            f"[0.1, 0.9]. Rooms whose plan below is not valid (waypoints less than {room.MIN_TRANSITION_DX:g} "
            f"apart in x, e.g. obstacles overlapping in x, or a path closer than {room.MIN_CLEARANCE:g} to an "
            "obstacle or wall) are redrawn, about 1 draw in 5. A scripted expert (the paper's simple heuristic) "
            f"passes each obstacle through the middle of its gap: waypoints start, (left face - {room.MARGIN:g}, "
            f"gap centre), (right face + {room.MARGIN:g}, gap centre) per obstacle, end; y(x) is the monotone "
            "PCHIP cubic through them, traversed by arc length "
            "with a minimum-jerk time law (zero velocity at both ends), and commanded at each step's phase "
            "(tau_k = k/99); the recorded positions are those the simulated servo reached. Conditions (the "
            "env's `condition`): `start_end`, the planned start (phase 0) and end (phase 1); `via_end`, the "
            "planned point at a phase drawn in [0.3, 0.7] and the end; `via`, that point only."
        ),
    )


def _metaworld_spec() -> SimSpec:
    from lerobot_cnmp.sims.metaworld.expert import MetaWorldExpert

    return SimSpec(
        env_config_cls=CNMPMetaWorldEnv,
        expert_cls=MetaWorldExpert,
        demo_length=150,
        default_episodes=20,
        default_conditions="reach-v3",
        feature_names={"action": ["dx", "dy", "dz", "gripper"], "agent_pos": ["hand_x", "hand_y", "hand_z", "gripper"],
                       "environment_state": ["obj_x", "obj_y", "obj_z", "goal_x", "goal_y", "goal_z"]},
        episode_label=lambda env: env.task_name,
        config_kwargs=lambda conditions: {"task": conditions},
        features_note=(
            "`observation.state` is MetaWorld's hand position (m) and gripper opening; `action` its (dx, dy, dz, "
            "gripper) in [-1, 1]; `observation.task_params` holds gamma = the first frame's main-object and goal "
            "positions (m), constant within an episode."
        ),
        description=(
            "A MetaWorld v3 task (metaworld 3.0.0: its Sawyer arm, physics, per-reset random object and goal "
            "placement and `info[\"success\"]`), wrapped by lerobot_cnmp.sims.metaworld.env without copying any of "
            "it, and demonstrated by MetaWorld's own scripted expert (metaworld.policies). The recorder's "
            "`--conditions` names the task (default reach-v3); every demo succeeds at its last frame."
        ),
    )


SIMS: dict[str, SimSpec] = {
    "cnmp_obstacle2d": _obstacle2d_spec(),
    "cnmp_obstacle2d_shared": _obstacle2d_shared_spec(),
    "cnmp_pickplace": _pickplace_spec(),
    "cnmp_weights": _weights_spec(),
    "cnmp_room": _room_spec(),
    "cnmp_so101": so101.sim_spec(),
    "cnmp_metaworld": _metaworld_spec(),
}

__all__ = ["CNMPObstacle2DEnv", "CNMPPickPlaceEnv", "CNMPRoomEnv", "CNMPWeightsEnv", "SIMS", "SimSpec",
           "OBSTACLE2D_GYM_ID", "PICKPLACE_GYM_ID", "ROOM_GYM_ID", "WEIGHTS_GYM_ID", "ENV_STATE_DIM"]

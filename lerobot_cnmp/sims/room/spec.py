"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec` of ``cnmp_room``: 1000 rooms with their planned
paths, the mask image, and the dataset card's prose."""

from __future__ import annotations

from typing import Any

from lerobot_cnmp.sims.registry import SimSpec, point_mass_feature_names
from lerobot_cnmp.sims.room.config import CNMPRoomEnv
from lerobot_cnmp.sims.room.expert import RoomExpert
from lerobot_cnmp.sims.room.model import DEFAULT_IMAGE_SIZE, MAX_CONDITIONS
from lerobot_cnmp.sims.room.planner import MARGIN, MIN_CLEARANCE, MIN_TRANSITION_DX
from lerobot_cnmp.sims.room.task import DEMO_LENGTH


def _room_config_kwargs(conditions: str) -> dict[str, Any]:
    # the recorder's --conditions is the env's `condition` option (checked by CNMPRoomEnv)
    return {"condition": conditions}


SPEC = SimSpec(
    env_config_cls=CNMPRoomEnv,
    expert_cls=RoomExpert,
    demo_length=DEMO_LENGTH,
    default_episodes=1000,
    default_conditions="start_end",
    feature_names=point_mass_feature_names(MAX_CONDITIONS),
    episode_label=lambda env: env.task.layout,
    config_kwargs=_room_config_kwargs,
    features_note=(
        "`observation.images.top` is the room's top-down binary mask, "
        f"{DEFAULT_IMAGE_SIZE} x {DEFAULT_IMAGE_SIZE} RGB (the three channels equal), 255 on the "
        "obstacles and 0 on the free floor, constant within an episode and stored as PNG frames (dtype "
        "`image`, no video). Image row 0 is the top of the room (y = 1) and column 0 its left side "
        f"(x = 0): pixel (r, c) covers x = (c + 0.5) / {DEFAULT_IMAGE_SIZE}, y = 1 - (r + 0.5) / "
        f"{DEFAULT_IMAGE_SIZE} at its centre; the "
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
        f"[0.1, 0.9]. Rooms whose plan below is not valid (waypoints less than {MIN_TRANSITION_DX:g} "
        f"apart in x, e.g. obstacles overlapping in x, or a path closer than {MIN_CLEARANCE:g} to an "
        "obstacle or wall) are redrawn, about 1 draw in 5. A scripted expert (the paper's simple heuristic) "
        f"passes each obstacle through the middle of its gap: waypoints start, (left face - {MARGIN:g}, "
        f"gap centre), (right face + {MARGIN:g}, gap centre) per obstacle, end; y(x) is the monotone "
        "PCHIP cubic through them, traversed by arc length "
        "with a minimum-jerk time law (zero velocity at both ends), and commanded at each step's phase "
        "(tau_k = k/99); the recorded positions are those the simulated servo reached. Conditions (the "
        "env's `condition`): `start_end`, the planned start (phase 0) and end (phase 1); `via_end`, the "
        "planned point at a phase drawn in [0.3, 0.7] and the end; `via`, that point only."
    ),
)

"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec` of ``cnmp_metaworld``: demos of MetaWorld's own
scripted experts on one v3 task (``--conditions`` names it) and the dataset card's prose."""

from __future__ import annotations

from lerobot_cnmp.sims.metaworld.config import CNMPMetaWorldEnv
from lerobot_cnmp.sims.metaworld.expert import MetaWorldExpert
from lerobot_cnmp.sims.registry import SimSpec

GAMMA_NAMES = ["obj_x", "obj_y", "obj_z", "goal_x", "goal_y", "goal_z"]


SPEC = SimSpec(
    env_config_cls=CNMPMetaWorldEnv,
    expert_cls=MetaWorldExpert,
    demo_length=150,
    default_episodes=20,
    default_conditions="reach-v3",
    feature_names={"action": ["dx", "dy", "dz", "gripper"], "agent_pos": ["hand_x", "hand_y", "hand_z", "gripper"],
                   "environment_state": GAMMA_NAMES, "task_params": GAMMA_NAMES},
    episode_label=lambda env: env.task_name,
    config_kwargs=lambda conditions: {"task": conditions},
    features_note=(
        "`observation.state` is MetaWorld's hand position (m) and gripper opening; `action` its (dx, dy, dz, "
        "gripper) in [-1, 1]; `observation.task_params` holds gamma = the first frame's main-object and goal "
        "positions (m), constant within an episode. Recorded with `--cameras`, the cameras are video features "
        "`observation.images.<name>` and gamma is kept as `ground_truth.task_params` (not an observation: no policy "
        "reads it)."
    ),
    description=(
        "A MetaWorld v3 task (metaworld 3.0.0: its Sawyer arm, physics, per-reset random object and goal "
        "placement and `info[\"success\"]`), wrapped by lerobot_cnmp.sims.metaworld.env without copying any of "
        "it, and demonstrated by MetaWorld's own scripted expert (metaworld.policies). The recorder's "
        "`--conditions` names the task (default reach-v3); every demo succeeds at its last frame."
    ),
)

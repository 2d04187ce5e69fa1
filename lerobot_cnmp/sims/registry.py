"""The recorder's registry of sims: what :mod:`lerobot_cnmp.record` needs to know about each sim
(:class:`SimSpec`), and :data:`SIMS`, the mapping ``--sim`` name -> spec whose entries are imported on first
access (a spec imports its sim's expert, and with it MuJoCo or a third-party package)."""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Callable


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


def condition_feature_names(max_conditions: int, sm_names: list[str]) -> list[str]:
    """Names of the entries of ``environment_state`` in the conditions layout (per slot k: ``ck_present``,
    ``ck_phase``, ``ck_<dim>`` for each SM dim, then ``ck_mask_<dim>``)."""
    names = []
    for k in range(max_conditions):
        names += [f"c{k}_present", f"c{k}_phase"]
        names += [f"c{k}_{n}" for n in sm_names]
        names += [f"c{k}_mask_{n}" for n in sm_names]
    return names


def point_mass_feature_names(max_conditions: int) -> dict[str, list[str]]:
    """Feature names of a point-mass sim (obstacle2d, room): action and ``agent_pos`` in (x, y), and the
    conditions layout of ``environment_state`` with ``max_conditions`` slots."""
    xy = ["x", "y"]
    return {"action": xy, "agent_pos": list(xy), "environment_state": condition_feature_names(max_conditions, xy)}


def records_only(sim: str, conditions_name: str, what: str) -> Callable[[str], dict[str, Any]]:
    """``config_kwargs`` of a sim that records one fixed set of episodes (its ``reset_options``): the only
    valid ``conditions`` is that set's name, and the env config takes no conditions option."""

    def config_kwargs(conditions: str) -> dict[str, Any]:
        if conditions != conditions_name:
            raise ValueError(f"{sim} records {what} only (conditions {conditions_name!r}), got {conditions!r}")
        return {}

    return config_kwargs


# --sim name -> "module:attribute" of its SimSpec
SPEC_PATHS = {
    "cnmp_obstacle2d": "lerobot_cnmp.sims.obstacle2d.spec:SPEC",
    "cnmp_obstacle2d_shared": "lerobot_cnmp.sims.obstacle2d.spec:SHARED_SPEC",
    "cnmp_pickplace": "lerobot_cnmp.sims.pickplace.spec:SPEC",
    "cnmp_weights": "lerobot_cnmp.sims.weights.spec:SPEC",
    "cnmp_room": "lerobot_cnmp.sims.room.spec:SPEC",
    "cnmp_so101": "lerobot_cnmp.sims.so101.spec:SPEC",
    "cnmp_metaworld": "lerobot_cnmp.sims.metaworld.spec:SPEC",
}


class _LazySims(Mapping):
    """``--sim`` name -> :class:`SimSpec`, each imported on first access."""

    def __init__(self, paths: dict[str, str]):
        self._paths = dict(paths)
        self._specs: dict[str, SimSpec] = {}

    def __getitem__(self, sim: str) -> SimSpec:
        if sim not in self._specs:
            if sim not in self._paths:
                raise KeyError(sim)
            module, attr = self._paths[sim].split(":")
            self._specs[sim] = getattr(importlib.import_module(module), attr)
        return self._specs[sim]

    def __iter__(self) -> Iterator[str]:
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)

    def __repr__(self) -> str:
        return f"SIMS({sorted(self._paths)})"


SIMS: Mapping[str, SimSpec] = _LazySims(SPEC_PATHS)

"""The sensorimotor (SM) space: which dataset features and dims the CNMP models, and what each dim does.

The paper's SM trajectory holds what the robot senses (joint or task-space positions, gripper, F/T) and what
it commands. A LeRobot dataset stores those in features such as ``observation.state`` and ``action``, whose
dims have ``names``. This module maps such features to SM dims and back:

- **commanded** dims come from ``action``: execution outputs them as the policy's action, whatever the
  action means (absolute joint targets, end-effector deltas, a gripper command). Every ``action`` dim must be
  in the SM.
- **sensed** dims come from any other (numeric, 1-D) feature, e.g. ``observation.state``: execution reads
  them from the live observation and conditions on them at the current phase (the paper's feedback).
- **γ** (task parameters): features read at an episode's first frame, constant for the episode.

Two layouts:

- *joint* (the default): SM = [sensed dims, action dims]. With ``observation.state`` present the SM is
  ``observation.state`` ⊕ ``action`` and nothing assumes that the sensed state equals a command (teleop
  data: a leader's action and a lagging follower's state).
- *tied* (``state_tracks_action=True``): SM = ``action`` and ``observation.state`` measures those same
  dims (a servo that reaches its command within a step, as in our sims): the sensed state is fed back as
  the SM point the previous command reached, and a PD law tracks the prediction.

A declaration (``CNMPConfig.sm``) lists entries ``"feature"`` (all its dims) or ``"feature:dim"`` (one dim,
by the dataset's dim name or by index). It resolves to the canonical ``"feature:index"`` form, saved in the
checkpoint's config, so execution needs no dataset.

**Task frames.** A sensed entry ``"feature:dim@task_feature:dim"`` is that dim *minus* one dim of γ: the
sensed value expressed relative to a task parameter read at the episode's first frame, e.g.
``"observation.state:ee_x@observation.environment_state:block_x"`` = the end effector's x relative to the
block's start (the object-centred frames of task-parameterized movement primitives). The model then learns
"reach 2.7 cm left of the block" as one number instead of a function of two inputs. Training subtracts γ
from the dataset's column, execution from the live reading, with the γ the episode started with. A dim may
appear both plain and in one or more frames; action dims cannot have a frame (they are output as they are).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

TASK_PARAMS = "observation.task_params"

FRAME_SEP = "@"
"""Separates an SM entry from the γ dim whose frame it is expressed in: ``"feature:dim@task_feature:dim"``."""

CONDITION_NAME_PREFIX = "c0_present"
"""The first dim name of an ``environment_state`` written in the CNMP condition layout by our recorder."""


def numeric_features(ds_features: dict[str, dict]) -> dict[str, dict]:
    """The dataset's 1-D numeric features (no images, videos, strings, or bookkeeping columns)."""
    skip = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
    out = {}
    for key, ft in ds_features.items():
        if key in skip or ft.get("dtype") in ("image", "video", "string"):
            continue
        if len(tuple(ft.get("shape", ()))) == 1:
            out[key] = ft
    return out


def features_from_policy(config) -> dict[str, dict]:
    """Dataset-like feature descriptions (shape, no names) from a config's input/output features."""
    out = {}
    for key, ft in {**(config.input_features or {}), **(config.output_features or {})}.items():
        if len(ft.shape) == 1:
            out[key] = {"dtype": "float32", "shape": tuple(ft.shape), "names": None}
    return out


def _raw_names(ft: dict):
    """A feature's dim names as stored; some datasets nest them: ``{"motors": [...]}``."""
    names = ft.get("names")
    return next(iter(names.values()), None) if isinstance(names, dict) else names


def _dim_names(ft: dict) -> list[str]:
    names = _raw_names(ft)
    size = int(tuple(ft["shape"])[0])
    if not names or len(names) != size:
        return [str(i) for i in range(size)]
    return [str(n) for n in names]


def is_condition_layout(ft: dict | None) -> bool:
    """Whether ``environment_state`` holds CNMP condition slots (our sims) rather than task data."""
    if ft is None:
        return False
    names = _raw_names(ft)
    if names:
        return str(names[0]) == CONDITION_NAME_PREFIX
    return True  # no names: a config built from shapes alone (the in-memory API) uses the slot layout


@dataclass(frozen=True)
class SMDim:
    feature: str
    index: int
    name: str
    origin: tuple[str, int] | None = None  # (γ feature, its dim): the SM dim is feature[index] - γ[origin]
    origin_name: str | None = None

    @property
    def key(self) -> str:
        base = f"{self.feature}:{self.index}"
        return base if self.origin is None else f"{base}{FRAME_SEP}{self.origin[0]}:{self.origin[1]}"

    @property
    def label(self) -> str:
        """The dim's name; in a task frame ``name-origin_name`` (e.g. ``ee_x-block_x``)."""
        return self.name if self.origin is None else f"{self.name}-{self.origin_name}"


@dataclass(frozen=True)
class SMSpec:
    """A resolved SM: frozen, so the index lists derived from it (read on every control step) are computed once."""

    dims: tuple[SMDim, ...]
    tied: bool
    task_features: tuple[tuple[str, int], ...]  # (feature, size)
    action_dim: int

    @property
    def size(self) -> int:
        return len(self.dims)

    @property
    def task_dim(self) -> int:
        return sum(n for _, n in self.task_features)

    @cached_property
    def commanded(self) -> list[int]:
        """SM indices of the action's dims, in the action's order."""
        by_index = {d.index: i for i, d in enumerate(self.dims) if d.feature == ACTION}
        return [by_index[k] for k in range(self.action_dim)]

    @cached_property
    def sensed(self) -> list[int]:
        """SM indices read from the live observation (tied: all, through ``observation.state``)."""
        if self.tied:
            return list(range(self.size))
        return [i for i, d in enumerate(self.dims) if d.feature != ACTION]

    @cached_property
    def origins(self) -> list[tuple[int, int]]:
        """(SM index, index into the concatenated γ vector) of every dim in a task frame."""
        offsets, at = {}, 0
        for key, size in self.task_features:
            offsets[key] = at
            at += size
        return [(i, offsets[d.origin[0]] + d.origin[1]) for i, d in enumerate(self.dims) if d.origin is not None]

    @cached_property
    def sensed_features(self) -> dict[str, list[tuple[int, int]]]:
        """Per observation feature, the (SM index, feature index) pairs it provides at execution."""
        out: dict[str, list[tuple[int, int]]] = {}
        if self.tied:
            out[OBS_STATE] = [(i, i) for i in range(self.size)]
            return out
        for i, d in enumerate(self.dims):
            if d.feature != ACTION:
                out.setdefault(d.feature, []).append((i, d.index))
        return out

    @property
    def names(self) -> list[str]:
        counts: dict[str, int] = {}
        for d in self.dims:
            counts[d.label] = counts.get(d.label, 0) + 1
        short = {OBS_STATE: "state", ACTION: "action"}
        return [d.label if counts[d.label] == 1 else f"{short.get(d.feature, d.feature)}.{d.label}" for d in self.dims]


def default_sm(ds_features: dict[str, dict], tied: bool) -> list[str]:
    if tied or OBS_STATE not in ds_features:
        return [ACTION]
    return [OBS_STATE, ACTION]


def default_task_features(ds_features: dict[str, dict], sm_features: set[str]) -> list[str]:
    """γ when the user declares none: ``observation.task_params`` if present, else an
    ``observation.environment_state`` that is not in the CNMP condition layout (e.g. an object position)."""
    if TASK_PARAMS in ds_features:
        return [TASK_PARAMS]
    env = ds_features.get(OBS_ENV_STATE)
    if env is not None and OBS_ENV_STATE not in sm_features and not is_condition_layout(env):
        return [OBS_ENV_STATE]
    return []


def _mismatch_hint(sm, ds_features: dict[str, dict]) -> str:
    """For an error against a declared SM: the declaration and the features, and what a mismatch usually is
    (a checkpoint whose SM was resolved on other features than the env's/robot's)."""
    if not sm:
        return ""
    shapes = {k: tuple(ft.get("shape", ())) for k, ft in numeric_features(ds_features).items()}
    return (f". The SM {list(sm)} does not match the features {shapes}: a checkpoint run on an env/robot other "
            "than the one it was trained on gives this (its SM is the checkpoint's, the features are the env's); "
            "run it on its own env/robot, or, when training, declare the SM for this dataset (--policy.sm)")


def resolve(sm: tuple[str, ...] | None, task_features: tuple[str, ...] | None, tied: bool,
            ds_features: dict[str, dict], use_task_params: bool | None = None) -> SMSpec:
    """The SM spec of a declaration against a dataset's (or a config's) features; a clear error for a
    feature or dim name the data lacks, a non-numeric feature, or a layout that cannot produce ``action``."""
    numeric = numeric_features(ds_features)
    if ACTION not in ds_features:
        raise ValueError(f"CNMP needs an {ACTION!r} feature (the commanded SM); the data has {sorted(ds_features)}")
    if ACTION not in numeric:
        raise ValueError(f"{ACTION!r} must be a flat numeric vector, got {ds_features[ACTION]}")
    entries = list(sm) if sm else default_sm(numeric, tied)
    dims: list[SMDim] = []

    def picks_of(entry: str, part: str, what: str) -> tuple[str, list[int], list[str]]:
        feature, _, dim = part.strip().partition(":")
        if feature not in ds_features:
            raise ValueError(f"{what} {entry!r}: the dataset has no feature {feature!r}; it has {sorted(ds_features)}")
        if feature not in numeric:
            raise ValueError(f"{what} {entry!r}: feature {feature!r} is not a flat numeric vector "
                             f"({ds_features[feature].get('dtype')}, shape {ds_features[feature].get('shape')})")
        names = _dim_names(numeric[feature])
        if not dim:
            return feature, list(range(len(names))), names
        if dim in names:
            return feature, [names.index(dim)], names
        if dim.lstrip("-").isdigit() and 0 <= int(dim) < len(names):
            return feature, [int(dim)], names
        raise ValueError(f"{what} {entry!r}: feature {feature!r} has no dim {dim!r}; its dims are {names}"
                         f"{_mismatch_hint(sm, ds_features)}")

    for entry in entries:
        head, sep, frame = str(entry).partition(FRAME_SEP)
        feature, picks, names = picks_of(entry, head, "SM entry")
        origin = origin_name = None
        if sep:
            if feature == ACTION or tied:
                raise ValueError(f"SM entry {entry!r}: only sensed dims can be expressed in a task frame "
                                 f"(the {ACTION!r} dims are output as they are)")
            o_feature, o_picks, o_names = picks_of(entry, frame, "task frame of SM entry")
            if len(o_picks) != 1 or len(picks) != 1:
                raise ValueError(f"SM entry {entry!r}: a task frame pairs one dim with one dim of γ "
                                 f"(\"feature:dim{FRAME_SEP}task_feature:dim\")")
            origin, origin_name = (o_feature, o_picks[0]), o_names[o_picks[0]]
        for k in picks:
            d = SMDim(feature, k, names[k], origin, origin_name)
            if d in dims:
                raise ValueError(f"SM entry {entry!r} repeats the dim {d.feature}:{d.label}")
            dims.append(d)
    action_dim = int(tuple(numeric[ACTION]["shape"])[0])
    got = {d.index for d in dims if d.feature == ACTION}
    if got != set(range(action_dim)):
        missing = [_dim_names(numeric[ACTION])[k] for k in range(action_dim) if k not in got]
        raise ValueError(f"the SM must hold every {ACTION!r} dim (execution outputs them); missing {missing}"
                         f"{_mismatch_hint(sm, ds_features)}")
    if tied:
        if any(d.feature != ACTION for d in dims):
            raise ValueError("state_tracks_action=True: the SM is the action alone (observation.state measures it)")
        state = numeric.get(OBS_STATE)
        if state is not None and tuple(state["shape"]) != (len(dims),):
            raise ValueError(
                f"state_tracks_action=True but {OBS_STATE!r} has shape {tuple(state['shape'])} and the SM "
                f"({ACTION!r}) has {len(dims)} dims: the sensed state is fed back as the SM, so they must match")
    sm_features = {d.feature for d in dims}
    if use_task_params is False:
        tasks: list[str] = []
    elif task_features is not None:
        tasks = list(task_features)
    else:
        tasks = default_task_features(ds_features, sm_features)
    if use_task_params and not tasks:
        raise ValueError(f"use_task_params=True but the dataset/env has no {TASK_PARAMS!r} feature (and no task "
                         f"features were declared); available: {sorted(ds_features)}")
    task_sizes = []
    for key in tasks:
        if key not in ds_features:
            raise ValueError(f"task feature {key!r}: the dataset has no such feature; it has {sorted(ds_features)}")
        if key not in numeric:
            raise ValueError(f"task feature {key!r} is not numeric ({ds_features[key].get('dtype')}, shape "
                             f"{ds_features[key].get('shape')}): γ must be a flat numeric vector")
        if key in sm_features:
            raise ValueError(f"feature {key!r} is declared both as SM and as task parameters γ")
        task_sizes.append((key, int(tuple(numeric[key]["shape"])[0])))
    for d in dims:
        if d.origin is not None and d.origin[0] not in tasks:
            raise ValueError(f"SM dim {d.key!r} is expressed in the frame of {d.origin[0]!r}, which is not among the "
                             f"task features γ {tasks}: declare it in task_features")
    return SMSpec(tuple(dims), tied, tuple(task_sizes), action_dim)

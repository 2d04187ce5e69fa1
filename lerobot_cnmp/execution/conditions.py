"""Conditions: the one condition type, its one validator, the parser of user conditions and the layout of
``observation.environment_state``.

A condition is a sensorimotor (SM) point the movement must pass through: a phase in [0, 1], the SM values at
that phase, and which SM dims it constrains (any subset). Its values are in **SM units**: the units of the data
the CNMP was trained on, dim by dim (a dataset's units; the arrays given to ``CNMPModel.fit``), never
normalized; the executor and the API normalize them with the SM statistics.

Every way a condition enters goes through :func:`check_points`:

* the Python API (``CNMPModel.predict``), the baselines and the sims build :class:`Condition` objects
  (:func:`check_conditions`);
* users give dicts by dim name (``--policy.conditions``, ``policy.set_conditions``, a JSON/YAML file; the
  async server uses the checkpoint's): :func:`parse_conditions` turns them into :class:`Condition` objects;
* envs write conditions into ``environment_state`` slots (:func:`encode_conditions`); the executor reads them
  back with :func:`decode_conditions` and checks them with :func:`check_points`.

Slot layout for SM dimension ``D`` and ``K`` slots (``K * (2 + 2D)`` floats)::

    slot k = [present, phase, value_1 .. value_D, mask_1 .. mask_D]

Unused slots are all zeros (``present = 0``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Condition:
    """One conditioning point: SM ``values`` (SM units, one per SM dim; NaN allowed outside ``dims``) at
    ``phase``; ``dims`` lists the constrained SM dims (all if None)."""

    phase: float
    values: tuple[float, ...]
    dims: tuple[int, ...] | None = None

    def mask(self) -> np.ndarray:
        m = np.zeros(len(self.values), dtype=np.float32)
        m[list(range(len(self.values)) if self.dims is None else list(self.dims))] = 1.0
        return m


# ---- the validator -----------------------------------------------------------------------------------------


def check_points(phase, values, mask, present=None, source: str = "condition") -> None:
    """Raise a ``ValueError`` naming the first bad point of ``phase`` [..., K], ``values`` / ``mask`` [..., K, D]
    (numpy arrays; ``present`` [..., K] marks the points in use, None: all): flags and phases must be finite,
    a used point's phase in [0, 1] and its values finite in every dim its mask constrains."""
    phase, values, mask = np.asarray(phase), np.asarray(values), np.asarray(mask)
    used = np.ones(phase.shape, dtype=bool) if present is None else np.asarray(present) > 0.5
    if present is not None and not np.isfinite(present).all():
        raise ValueError(f"{source}: a presence flag is NaN or infinite")

    def first(bad: np.ndarray) -> str:
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        return f"{source} {at[-1]}" + (f" (env {at[0]})" if len(at) > 1 else "")

    if not np.isfinite(phase).all():
        raise ValueError(f"{first(~np.isfinite(phase))}: its phase is NaN or infinite")
    outside = used & ((phase < 0) | (phase > 1))
    if outside.any():
        raise ValueError(f"{first(outside)}: phase {float(phase[outside][0]):g} is outside [0, 1]")
    bad = used & ((~np.isfinite(values)) & (mask > 0.5)).any(-1)
    if bad.any():
        raise ValueError(f"{first(bad)}: NaN or infinite values in a constrained dim")


def check_conditions(conditions, sm_dim: int, capacity: int | None = None) -> list[Condition]:
    """Validate :class:`Condition` objects against an SM of ``sm_dim`` dims and ``capacity`` points (None: no
    limit); returns them as a list."""
    conditions = list(conditions)
    if capacity is not None and len(conditions) > capacity:
        raise ValueError(f"{len(conditions)} conditions given; this CNMP takes at most {capacity} (max_conditions)")
    for k, c in enumerate(conditions):
        if not isinstance(c, Condition):
            raise TypeError(f"condition {k} is a {type(c).__name__}, not a Condition")
        if len(c.values) != sm_dim:
            raise ValueError(f"condition {k} has {len(c.values)} values; the SM has {sm_dim} dims")
        if c.dims is not None and (not c.dims or min(c.dims) < 0 or max(c.dims) >= sm_dim):
            raise ValueError(f"condition {k} constrains dims {c.dims}; valid SM dims are 0..{sm_dim - 1}")
    if conditions:
        phase = np.array([_float(c.phase) for c in conditions])
        values = np.array([[_float(v) for v in c.values] for c in conditions])
        check_points(phase, values, np.stack([c.mask() for c in conditions]))
    return conditions


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        raise ValueError(f"condition value {x!r} is not a number") from None


# ---- the parser of user conditions (dicts by dim name) ---------------------------------------------------------


def load_condition_spec(spec) -> list:
    """Conditions as a list of dicts (or :class:`Condition` objects) from: a list/dict, a JSON string, or a path
    to a JSON/YAML file."""
    if spec is None:
        return []
    if isinstance(spec, (str, Path)):
        text = str(spec).strip()
        if not text:
            return []
        path = Path(text)
        import yaml

        if text[0] not in "[{" and path.suffix.lower() in (".json", ".yaml", ".yml"):
            if not path.is_file():
                raise FileNotFoundError(f"conditions file {path} does not exist")
            text = path.read_text()
            spec = yaml.safe_load(text) if path.suffix.lower() in (".yaml", ".yml") else json.loads(text)
        else:
            # JSON, or YAML flow style (what draccus hands over from the command line: it parses a CLI value
            # as YAML and a str field gets the Python repr of the list)
            try:
                spec = yaml.safe_load(text)
            except yaml.YAMLError as e:
                raise ValueError(f"conditions {text!r} are neither JSON/YAML nor a path to a .json/.yaml file: {e}") from e
            if isinstance(spec, str):
                raise ValueError(f"conditions {text!r} are neither JSON/YAML nor a path to a .json/.yaml file (no such "
                                 "file)")
    if isinstance(spec, (dict, Condition)):
        spec = [spec]
    if not isinstance(spec, (list, tuple)) or not all(isinstance(c, (dict, Condition)) for c in spec):
        raise ValueError(f"conditions must be a dict or a list of dicts (e.g. [{{\"t\": 1.0, \"x\": 0.5}}]), got {spec!r}")
    return [c if isinstance(c, Condition) else dict(c) for c in spec]


def dim_lookup(spec, sm_names=None) -> dict[str, list[int]]:
    """Every name a user may give an SM dim: the dataset's dim name (all SM dims of that name, e.g. the state
    and the action of one joint), the SM's unique name (``state.x`` when the name repeats; ``sm_names``, saved
    in the checkpoint), ``feature:name`` and ``feature:index``."""
    short = {"observation.state": "state", "action": "action"}
    unique = list(sm_names) if sm_names is not None and len(sm_names) == spec.size else list(spec.names)
    out: dict[str, list[int]] = {}
    for i, (d, u) in enumerate(zip(spec.dims, unique, strict=True)):
        prefix = f"{short.get(d.feature, d.feature)}."
        bare = u[len(prefix):] if u.startswith(prefix) and u != d.name else u
        for key in {bare, u, f"{d.feature}:{bare}", d.key}:
            out.setdefault(key, [])
            if i not in out[key]:
                out[key].append(i)
    return out


def parse_conditions(raw, spec, demo_duration_s: float | None, capacity: int, sm_names=None) -> list[Condition]:
    """User conditions as validated :class:`Condition` objects. Each dict has ``t`` (phase in [0, 1]) or
    ``time_s`` (seconds into the movement, / demo_duration_s) and values by dim name (see :func:`dim_lookup`);
    :class:`Condition` objects pass as they are. Any error names the condition and the problem."""
    items = load_condition_spec(raw)
    if len(items) > capacity:
        raise ValueError(f"{len(items)} conditions given; this CNMP takes at most {capacity} (max_conditions)")
    names = dim_lookup(spec, sm_names)
    display = list(sm_names) if sm_names is not None and len(sm_names) == spec.size else spec.names
    out = []
    for k, item in enumerate(items):
        if isinstance(item, Condition):
            out.append(item)
            continue
        if ("t" in item) == ("time_s" in item):
            raise ValueError(f"condition {k} {item}: give its time as exactly one of 't' (phase in [0, 1]) or "
                             "'time_s' (seconds from the movement's start)")
        if "t" in item:
            phase = _number(item.pop("t"), k, "t")
        else:
            seconds = _number(item.pop("time_s"), k, "time_s")
            if not demo_duration_s:
                raise ValueError(f"condition {k}: 'time_s' needs the demonstrations' duration (demo_duration_s), "
                                 "which this checkpoint does not have; give the phase 't'")
            phase = seconds / demo_duration_s
        if not 0.0 <= phase <= 1.0:
            raise ValueError(f"condition {k}: phase {phase:g} is outside [0, 1] (the movement lasts "
                             f"{demo_duration_s or '?'} s)")
        if not item:
            raise ValueError(f"condition {k} constrains no dim; give values by name, one of {sorted(names)}")
        values = [math.nan] * spec.size
        dims: set[int] = set()
        for name, value in item.items():
            name = str(name)  # YAML reads a dim named 1 as an int
            if name not in names:
                raise ValueError(f"condition {k}: unknown dim {name!r}; the SM's dims are {sorted(names)}")
            v = _number(value, k, name)
            for i in names[name]:
                if i in dims and values[i] != v:
                    raise ValueError(f"condition {k} gives SM dim {display[i]!r} two values")
                values[i] = v
                dims.add(i)
        out.append(Condition(float(phase), tuple(values), tuple(sorted(dims))))
    return check_conditions(out, spec.size)


def _number(value, k: int, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"condition {k}: {name!r} = {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"condition {k}: {name!r} = {value!r} is NaN or infinite")
    return v


# ---- the environment_state slot layout ----------------------------------------------------------------------


def slot_size(sm_dim: int) -> int:
    return 2 + 2 * sm_dim


def layout_size(sm_dim: int, max_conditions: int) -> int:
    return max_conditions * slot_size(sm_dim)


def encode_conditions(conditions: list[Condition], sm_dim: int, max_conditions: int) -> np.ndarray:
    """Pack conditions into the flat ``environment_state`` vector (float32)."""
    if len(conditions) > max_conditions:
        raise ValueError(f"{len(conditions)} conditions given but the layout has {max_conditions} slots")
    out = np.zeros((max_conditions, slot_size(sm_dim)), dtype=np.float32)
    for k, c in enumerate(check_conditions(conditions, sm_dim)):
        out[k, 0] = 1.0
        out[k, 1] = c.phase
        out[k, 2 : 2 + sm_dim] = np.asarray(c.values, dtype=np.float32)
        out[k, 2 + sm_dim :] = c.mask()
    return out.reshape(-1)


def decode_conditions(env_state, sm_dim: int):
    """Split ``environment_state`` ``[..., K*(2+2D)]`` into ``(present [...,K], phase [...,K],
    values [...,K,D], mask [...,K,D])``. Works on numpy arrays and torch tensors alike."""
    size = env_state.shape[-1]
    if size % slot_size(sm_dim) != 0:
        raise ValueError(
            f"environment_state has {size} values, not a multiple of the slot size {slot_size(sm_dim)} "
            f"(= 2 + 2 * SM dimension {sm_dim}); it does not follow the CNMP condition layout"
        )
    slots = env_state.reshape(*env_state.shape[:-1], size // slot_size(sm_dim), slot_size(sm_dim))
    return slots[..., 0], slots[..., 1], slots[..., 2 : 2 + sm_dim], slots[..., 2 + sm_dim :]


def conditions_from_vector(env_state: np.ndarray, sm_dim: int) -> list[Condition]:
    """Inverse of :func:`encode_conditions` for one episode (numpy)."""
    present, phase, values, mask = decode_conditions(np.asarray(env_state), sm_dim)
    check_points(phase, values, mask, present, source="environment_state condition")
    out = []
    for k in range(present.shape[-1]):
        if present[k] > 0.5:
            dims = tuple(int(i) for i in np.flatnonzero(mask[k] > 0.5))
            out.append(Condition(float(phase[k]), tuple(float(v) for v in values[k]), dims))
    return out

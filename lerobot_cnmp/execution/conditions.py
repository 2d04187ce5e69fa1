"""Conditions as data: the layout of ``observation.environment_state``.

A condition is a sensorimotor (SM) point the movement must satisfy: a phase ``t`` in [0, 1], the SM
values at that phase, and which SM dimensions are constrained (a 0/1 mask, so any subset of dims can be
conditioned). Envs write an episode's conditions into ``environment_state`` and the policy reads them
back; both use this module, so the layout is written once.

Layout for SM dimension ``D`` and ``K`` slots (``K * (2 + 2D)`` floats)::

    slot k = [present, phase, value_1 .. value_D, mask_1 .. mask_D]

Unused slots are all zeros (``present = 0``). Values are in the SM's own units (the dataset's units of each
SM dim); the policy normalizes them with its SM statistics (``modeling_cnmp.SMNormalizer``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Condition:
    """One conditioning point: SM ``values`` at ``phase``; ``dims`` lists the constrained dims (all if None)."""

    phase: float
    values: tuple[float, ...]
    dims: tuple[int, ...] | None = None

    def mask(self) -> np.ndarray:
        m = np.zeros(len(self.values), dtype=np.float32)
        m[list(range(len(self.values)) if self.dims is None else list(self.dims))] = 1.0
        return m


def slot_size(sm_dim: int) -> int:
    return 2 + 2 * sm_dim


def layout_size(sm_dim: int, max_conditions: int) -> int:
    return max_conditions * slot_size(sm_dim)


def encode_conditions(conditions: list[Condition], sm_dim: int, max_conditions: int) -> np.ndarray:
    """Pack conditions into the flat ``environment_state`` vector (float32)."""
    if len(conditions) > max_conditions:
        raise ValueError(f"{len(conditions)} conditions given but the layout has {max_conditions} slots")
    out = np.zeros((max_conditions, slot_size(sm_dim)), dtype=np.float32)
    for k, c in enumerate(conditions):
        if len(c.values) != sm_dim:
            raise ValueError(f"condition {k} has {len(c.values)} values, expected SM dimension {sm_dim}")
        if not 0.0 <= c.phase <= 1.0:
            raise ValueError(f"condition {k} has phase {c.phase}, outside [0, 1]")
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
    out = []
    for k in range(present.shape[-1]):
        if present[k] > 0.5:
            dims = tuple(int(i) for i in np.flatnonzero(mask[k] > 0.5))
            out.append(Condition(float(phase[k]), tuple(float(v) for v in values[k]), dims))
    return out

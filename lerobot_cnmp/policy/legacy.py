"""Older CNMP config layouts -> today's: the one upgrade applied to every config dict before it is decoded.

Checkpoints' ``config.json``, ``train_config.json`` and ``configs/*.json`` written by older versions held at
their top level what now lives in the sub-configs ``execution``, ``sampling`` and ``mixture``, and two mixture
options that are gone. :func:`upgrade_config_dict` moves the first into their section and drops the second, so
such files load and act as they did. ``CNMPConfig`` applies it whenever draccus decodes a CNMP config from a
dict (``--policy.path``, ``PreTrainedConfig.from_pretrained``, ``--config_path``, resuming a run).

The name lists below are the frozen old layout, not a copy of today's fields: new settings never go flat.
"""

from __future__ import annotations

import functools
import logging
import typing
from typing import Any

logger = logging.getLogger(__name__)

FLAT_EXECUTION = ("control_fps", "phase_step", "online_feedback", "condition_on_start", "feedback_dims",
                  "tracking_dims", "phase_stop_threshold", "pd_kp", "pd_kd", "pd_dims", "sigma_scaled_gains",
                  "sigma_ref", "kp_min", "kp_max", "numpy_execution")
"""The execution settings held at the top level before ``execution`` existed (None there: not given)."""

OLD_LAYOUT_MARKERS = ("online_feedback", "condition_on_start", "sigma_scaled_gains", "numpy_execution", "pd_kp")
"""All set (not None): a whole config written before ``execution`` existed, taken as written."""

FLAT_SAMPLING = ("n_max_context", "m_max_targets", "context_in_targets", "partial_obs_prob", "sensed_obs_prob",
                 "feedback_draw_weight", "feedback_draw_queries", "draws_per_sample")
FLAT_MIXTURE = ("gate_entropy_coef", "batch_entropy_coef", "shared_decoder_layers", "assignment_draws",
                "unconditional_nll_coef", "expert_selection", "mode_switch_margin")

REMOVED = {"mixture_nll": "assigned", "gate_commit": "always"}
"""Removed mixture options -> the one behaviour kept (training only: a checkpoint acts the same without them)."""


def upgrade_config_dict(d: dict[str, Any]) -> dict[str, Any]:
    """A CNMP config dict (as read from JSON, CLI overrides merged in) in today's layout; ``d`` is not changed.

    - Flat ``sampling`` / ``mixture`` fields move into their section.
    - Flat execution fields move into ``execution``. A whole old config (every marker of
      ``OLD_LAYOUT_MARKERS`` set) is taken as written, None values included (``phase_stop_threshold: null`` =
      never stop), with the phase-stop semantics it was written for: ``phase_stop_units="normalized"`` and no
      timeout. Otherwise only the flat fields that are not None are moved.
    - ``mixture_nll`` and ``gate_commit`` are dropped, with a warning if they held another value than the
      behaviour kept.
    - A trained policy's config (``dataset_fps`` set) without ``linear_task_term``, written before that
      setting existed, gets ``linear_task_term = false``: its network has no such term.

    A value already in a section (e.g. ``--policy.execution.pd_kp=0.5`` given with ``--policy.path``) wins
    over the flat one."""
    d = dict(d)
    for name, kept in REMOVED.items():
        value = d.pop(name, None)
        if value not in (None, kept):
            logger.warning("CNMP config: %s=%r is no longer an option (only %r remains); it set training only, "
                           "so the checkpoint acts as before", name, value, kept)
    if d.get("dataset_fps") is not None and "linear_task_term" not in d:
        d["linear_task_term"] = False
    _nest(d, "sampling", {n: d.pop(n) for n in FLAT_SAMPLING if n in d})
    _nest(d, "mixture", {n: d.pop(n) for n in FLAT_MIXTURE if n in d})
    flat = {n: d.pop(n) for n in FLAT_EXECUTION if n in d}
    if flat and all(flat.get(k) is not None for k in OLD_LAYOUT_MARKERS):
        flat.update(phase_stop_units="normalized", phase_stop_timeout_s=None)
    else:
        flat = {k: v for k, v in flat.items() if v is not None}
    _nest(d, "execution", flat)
    return d


def _nest(d: dict[str, Any], section: str, flat: dict[str, Any]) -> None:
    if not flat:
        return
    nested = d.get(section)
    if nested is None:
        nested = {}
    if not isinstance(nested, dict):
        raise ValueError(f"CNMP config: {sorted(flat)} given both flat and in {section!r}, which is not a dict")
    logger.debug("CNMP config: old top-level settings %s moved under %r", sorted(flat), section)
    d[section] = {**flat, **nested}


def decode_with_upgrade(config_cls: type) -> None:
    """Make draccus apply :func:`upgrade_config_dict` to every dict it decodes into ``config_cls`` (or a
    subclass): parsed as itself (``PreTrainedConfig.from_pretrained``, ``--policy.path``) or as the ``policy``
    choice of a pipeline config (``--config_path``, a run's ``train_config.json``).

    draccus has no per-class hook that keeps a choice class's fields on the command line (a decoder
    registered with ``draccus.decode.register`` turns ``--policy.*`` into one opaque option), so this wraps
    draccus' dataclass decoder, through which both paths go; other classes' dicts pass through untouched."""
    from draccus.parsers import decoding

    decode = getattr(decoding.decode_dataclass, "__wrapped__", decoding.decode_dataclass)
    upgraded = set(getattr(decoding.decode_dataclass, "upgraded_classes", ())) | {config_cls}

    @functools.wraps(decode)
    def decode_dataclass(cls, d, path=()):
        origin = typing.get_origin(cls) or cls
        if isinstance(d, dict) and isinstance(origin, type) and issubclass(origin, tuple(upgraded)):
            d = upgrade_config_dict(d)
        return decode(cls, d, path)

    decode_dataclass.upgraded_classes = tuple(upgraded)
    decoding.decode_dataclass = decode_dataclass
    decoding.get_decoding_fn.cache_clear()  # its cached decoders hold the function they were built with

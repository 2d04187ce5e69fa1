"""One settings reader for the benches, built from the config dataclasses: a dataclass's fields become
command-line options (name, type, choices) and come back as keyword arguments, so no bench keeps its own copy
of a config's field names, types or allowed values.

    p = argparse.ArgumentParser()
    add_dataclass_arguments(p, MixtureConfig)              # --assignment_draws INT, --unconditional_nll_coef FLOAT, ...
    overrides = dataclass_settings(p.parse_args(), MixtureConfig)   # only the options given: {"assignment_draws": 1}

Each option defaults to None, which means "not given: the config's value" (the committed config's, else the
dataclass's default, shown in the option's help). The option's type follows the field's annotation:
``int``, ``float``, ``str``, ``bool`` (``true``/``false``), ``X | None`` as ``X``, ``tuple[X, ...]`` as one or
more values, ``Literal[...]`` as its choices. Fields that are dataclasses or dicts (nested sections) have no
flat option; asking for one by name is an error.
"""

from __future__ import annotations

import dataclasses
import types
import typing

_BOOL_WORDS = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}


def parse_bool(text: str) -> bool:
    """``true``/``false`` (also 1/0, yes/no, any case) as a bool; anything else is an argparse error."""
    import argparse

    try:
        return _BOOL_WORDS[str(text).strip().lower()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}") from None


def _strip_optional(kind):
    """``X | None`` / ``Optional[X]`` -> X; anything else unchanged."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return kind


def option_spec(cls, name: str) -> dict:
    """argparse keywords (``type``, ``nargs``, ``choices``) for field ``name`` of dataclass ``cls``; raises
    TypeError for a field with no flat command-line form (a nested dataclass, a dict, a union of types)."""
    kind = _strip_optional(typing.get_type_hints(cls)[name])
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Literal:
        return {"type": type(args[0]), "choices": args}
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return {"type": args[0], "nargs": "+"}
    if kind is bool:
        return {"type": parse_bool}
    if kind in (int, float, str):
        return {"type": kind}
    raise TypeError(f"{cls.__name__}.{name} ({kind}) has no command-line form: give its sub-config's fields instead")


def _names(cls, only) -> list[str]:
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    init = [f.name for f in dataclasses.fields(cls) if f.init]
    if only is None:
        return [n for n in init if _has_option(cls, n)]
    unknown = [n for n in only if n not in init]
    if unknown:
        raise ValueError(f"{cls.__name__} has no field {unknown}")
    return list(only)


def _has_option(cls, name: str) -> bool:
    try:
        option_spec(cls, name)
    except TypeError:
        return False
    return True


def _default(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def add_dataclass_arguments(parser, cls, only=None, choices: dict | None = None) -> None:
    """One ``--<field>`` option per field of dataclass ``cls`` (those named in ``only``, in that order; else every
    field with a flat form), default None ("the config's"). ``choices``: allowed values of fields that the
    dataclass checks against a fixed set in code rather than in their annotation (``{"field": values}``)."""
    choices = choices or {}
    unknown = set(choices) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ValueError(f"choices name fields {sorted(unknown)} that {cls.__name__} does not have")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for name in _names(cls, only):
        spec = option_spec(cls, name)
        if name in choices:
            spec["choices"] = tuple(choices[name])
        parser.add_argument(f"--{name}", default=None, **spec,
                            help=f"{cls.__name__}.{name} (default: the config's; {cls.__name__}'s is "
                                 f"{_default(fields[name])!r})")


def dataclass_settings(args, cls, only=None) -> dict:
    """The options of :func:`add_dataclass_arguments` that were given (not None), as keyword arguments of
    ``cls`` (one-or-more values as tuples). ``args``: an argparse Namespace or a mapping."""
    values = args if isinstance(args, dict) else vars(args)
    out = {}
    for name in _names(cls, only):
        value = values.get(name)
        if value is not None:
            out[name] = tuple(value) if isinstance(value, list) else value
    return out

"""One declaration per setting: a dataclass field that carries its default, range and description.

From that one place come the ROS parameter declarations of a node (`declare_settings`, with
descriptors and ranges), the command-line flags of the in-process tools (`add_flags` /
`from_flags`), the checks both apply (`check`) and the generated parameter reference in
docs/PARAMETERS.md (`reference_rows`). Fields without `setting` metadata are not settings (derived
values); a field whose default is itself a settings dataclass contributes its own settings, flat.

ROS-free at import: rclpy is only touched by `declare_settings`.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
from typing import Any


class SettingError(ValueError):
    """A value a setting cannot take; the message names the setting and what would be valid."""


def setting(default, description: str, lo=None, hi=None, choices=None, name: str | None = None, read_only: bool = True):
    """A dataclass field that is a setting. `name` is its ROS parameter and flag name when it differs
    from the field's; `read_only` False lets a running node change it (ROS parameters only)."""
    meta = {"description": description, "lo": lo, "hi": hi, "choices": tuple(choices) if choices else None}
    meta.update(name=name, read_only=read_only)
    return dataclasses.field(default=default, metadata={"setting": meta})


@dataclasses.dataclass(frozen=True)
class Spec:
    field: str  # the dataclass field
    name: str  # the ROS parameter and flag name
    default: Any
    description: str
    lo: Any = None
    hi: Any = None
    choices: tuple | None = None
    read_only: bool = True
    path: tuple[str, ...] = ()  # enclosing settings dataclasses' fields (a nested config)


def specs(cls_or_obj, path: tuple[str, ...] = ()) -> list[Spec]:
    """The settings of a dataclass (class or instance: an instance's values are the defaults), nested ones flat."""
    out = []
    for f in dataclasses.fields(cls_or_obj):
        default = getattr(cls_or_obj, f.name) if not isinstance(cls_or_obj, type) else f.default
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            out += specs(default, (*path, f.name))
            continue
        meta = f.metadata.get("setting")
        if meta is None:
            continue
        out.append(
            Spec(
                f.name,
                meta["name"] or f.name,
                default,
                meta["description"],
                meta["lo"],
                meta["hi"],
                meta["choices"],
                meta["read_only"],
                path,
            )
        )
    return out


def check(spec: Spec, value):
    """`value` as the setting's type, or SettingError naming the setting, the value and what is valid."""
    d = spec.default
    if isinstance(d, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(d, tuple) and isinstance(value, list):
        value = tuple(value)
    if type(value) is not type(d):
        raise SettingError(f"'{spec.name}' must be of type {type(d).__name__}, got {value!r}")
    if isinstance(d, tuple) and d and any(type(v) is not type(d[0]) for v in value):
        raise SettingError(f"'{spec.name}' must be a list of {type(d[0]).__name__}, got {list(value)!r}")
    if spec.lo is not None and not isinstance(value, (str, bool, tuple)) and not spec.lo <= value <= spec.hi:
        raise SettingError(f"'{spec.name}'={value!r} is outside [{spec.lo}, {spec.hi}]")
    if spec.choices and value not in spec.choices:
        raise SettingError(f"'{spec.name}'={value!r} is invalid: expected one of {', '.join(spec.choices)}")
    return value


def build(cls, values: dict[str, Any]):
    """An instance of `cls` with `values` (by setting name) checked; nested configs are rebuilt. Raises
    SettingError for a value a setting cannot take or a name that is no setting."""
    base = cls()
    known = {s.name: s for s in specs(base)}
    unknown = [n for n in values if n not in known]
    if unknown:
        raise SettingError(unknown_message(unknown[0], known))
    changes: dict[tuple[str, ...], dict[str, Any]] = {}
    for name, value in values.items():
        s = known[name]
        changes.setdefault(s.path, {})[s.field] = check(s, value)
    return _replace(base, (), changes)


def _replace(obj, path, changes):
    nested = {
        f.name: _replace(getattr(obj, f.name), (*path, f.name), changes)
        for f in dataclasses.fields(obj)
        if dataclasses.is_dataclass(getattr(obj, f.name))
    }
    return dataclasses.replace(obj, **nested, **changes.get(path, {}))


def unknown_message(name: str, known, removed: dict[str, str] | None = None) -> str:
    """'unknown setting' with a did-you-mean, or why it was removed and what replaces it."""
    if removed and name in removed:
        return f"'{name}' was removed: {removed[name]}"
    close = difflib.get_close_matches(name, list(known), n=1)
    return f"'{name}' is not a setting" + (f" (did you mean '{close[0]}'?)" if close else "")


# -- ROS parameters -------------------------------------------------------------------------------
def declare_settings(node, cls, removed: dict[str, str] | None = None):
    """Declare every setting of `cls` on `node` (descriptor with description and range) and return the
    instance the node was given. ParameterError (uav_common.ros_params) names a bad value, and any
    parameter the node was given that nothing declares (`removed` says why for retired ones)."""
    from .ros_params import ParameterError, declare

    values = {}
    for s in specs(cls):
        default = list(s.default) if isinstance(s.default, tuple) else s.default
        values[s.name] = declare(node, s.name, default, s.description, s.lo, s.hi, s.choices, s.read_only)
    check_undeclared(node, removed)
    try:
        return build(cls, values)
    except SettingError as e:
        raise ParameterError(f"parameter {e}") from None


def check_undeclared(node, removed: dict[str, str] | None = None) -> None:
    """ParameterError for a parameter the node was given (-p, a params file) that it does not declare:
    a typo or a retired parameter (`removed` says why and what replaces it), never silently ignored."""
    from .ros_params import ParameterError

    declared = set(node._parameters)  # rclpy keeps the declared parameters there
    for name in getattr(node, "_parameter_overrides", {}):
        if name not in declared:
            raise ParameterError(f"parameter {unknown_message(name, declared, removed)}")


# -- command-line flags ---------------------------------------------------------------------------
def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_flags(parser: argparse.ArgumentParser, cls, skip=(), title: str | None = None) -> None:
    """Add a flag for each setting of `cls` but those in `skip`, defaulting to None (= not given)."""
    group = parser.add_argument_group(title) if title else parser
    for s in specs(cls):
        if s.name in skip:
            continue
        kw: dict[str, Any] = {"default": None, "dest": f"setting_{s.name}", "metavar": s.name.upper()}
        rng = f" [{s.lo}, {s.hi}]" if s.lo is not None else ""
        kw["help"] = f"{s.description}{rng} (default: {fmt(s.default)})"
        if isinstance(s.default, bool):
            kw["action"] = argparse.BooleanOptionalAction
            del kw["metavar"]
        elif isinstance(s.default, tuple):
            kw.update(nargs="+", type=type(s.default[0]) if s.default else str)
        else:
            kw["type"] = type(s.default)
            if s.choices:
                kw["choices"] = s.choices
        group.add_argument(flag(s.name), **kw)


def refuse_retired_flags(parser: argparse.ArgumentParser, argv: list[str], retired: dict[str, str]) -> None:
    """parser.error for the first retired flag in `argv` (`--flag` or `--flag=value`), saying what replaces it."""
    for arg in argv:
        name = arg.split("=", 1)[0]
        if name in retired:
            parser.error(f"{name} was removed: {retired[name]}")


def given_flags(ns: argparse.Namespace) -> dict[str, Any]:
    """The settings given on the command line (by setting name)."""
    return {k[len("setting_") :]: v for k, v in vars(ns).items() if k.startswith("setting_") and v is not None}


def fmt(value) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(map(str, value)) + "]"
    if isinstance(value, bool):
        return str(value).lower()
    return repr(value) if isinstance(value, str) else str(value)


def reference_rows(cls) -> list[str]:
    """Markdown table rows (name, default, range, description) for the parameter reference."""
    rows = ["| parameter | default | range | description |", "|---|---|---|---|"]
    for s in specs(cls):
        rng = f"[{s.lo}, {s.hi}]" if s.lo is not None else ", ".join(s.choices) if s.choices else ""
        rw = "" if s.read_only else " (changes at run time)"
        rows.append(f"| `{s.name}` | `{fmt(s.default)}` | {rng} | {s.description}{rw} |")
    return rows

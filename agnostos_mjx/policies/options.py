"""A built-in policy's options: a dataclass of typed fields, each with a default and a help
line, which ``--policy-arg KEY=VALUE`` pairs fill (`parse_options`).

A built-in policy declares its options type (``TimingOptions``, ``XicmOptions``, ...) in a
module that imports neither JAX nor MuJoCo, so that a bad ``--policy-arg`` is one line of
error before either loads and ``--policy-arg help`` lists the options (`describe`) without
loading the policy.  The policy is constructed from the filled dataclass.  Values are
checked against the fields' annotations (str, int, float, bool, dict, Any and their unions
with None); an int is taken for a float, a number for a str.  `PolicyOptions.from_config`
is where a policy's own command-line flags (X-ICM's ``--selection``, ``--llm-url``, ...)
fill its options.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any


class OptionsError(ValueError):
    """A --policy-arg that the policy's options do not take: one line, naming the fix."""


def option(default: Any, help: str) -> Any:
    """A field of an options type: its default and its one-line help."""
    if isinstance(default, list | dict):
        return field(default_factory=lambda: type(default)(default), metadata={"help": help})
    return field(default=default, metadata={"help": help})


@dataclass
class PolicyOptions:
    """Base of the options types: checks every field's value against its annotation on
    construction (so a directly built options object is checked as a parsed one), then
    `check` for what a type cannot say (ranges)."""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in fields(self):
            value = getattr(self, f.name)
            if value is f.default:  # a default is trusted (it may be a sentinel)
                continue
            try:
                setattr(self, f.name, coerce(value, hints[f.name]))
            except TypeError as e:
                raise OptionsError(f"{f.name}={json.dumps(value, default=repr)}: {e}") from None
        self.check()

    def check(self) -> None:
        """Constraints beyond the types, as an OptionsError.  Default: none."""

    @classmethod
    def program_fields(cls) -> tuple[str, ...]:
        """The options the policy's shared programs (`Policy.warm_up`) are built from: the
        warm-up gets these alone, and its once-per-machine marker is keyed by them.
        Default: every option."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_config(cls, cfg: Any) -> dict[str, Any]:
        """The options that the run's own flags set, `cfg` being its EvalConfig (untyped
        here: the evaluator imports this layer, not the other way round); its --policy-arg
        pairs override them.  Default: none."""
        return {}

    def values(self) -> dict[str, Any]:
        """Every option by name (the keyword form that `parse_options` takes back)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def coerce(value: Any, kind: Any) -> Any:
    """`value` as annotation `kind` says, or a TypeError saying what was expected."""
    if kind is Any:
        return value
    if typing.get_origin(kind) in (types.UnionType, typing.Union):
        for member in typing.get_args(kind):
            try:
                return coerce(value, member)
            except TypeError:
                pass
        raise TypeError(f"expected {_expected(kind)}")
    if kind is type(None):
        if value is None:
            return None
    elif kind is bool:
        if isinstance(value, bool):
            return value
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif kind is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif kind is str:
        if isinstance(value, str):
            return value
        if isinstance(value, int | float) and not isinstance(value, bool):
            return json.dumps(value)  # size=128 meant as text: the text typed
    elif typing.get_origin(kind) is dict or kind is dict:
        if isinstance(value, str):  # a JSON object given as text (keys='{"a": "b"}')
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                pass
        if isinstance(value, Mapping):
            return dict(value)
    raise TypeError(f"expected {_expected(kind)}")


def _expected(kind: Any) -> str:
    if typing.get_origin(kind) in (types.UnionType, typing.Union):
        return " or ".join(_expected(m) for m in typing.get_args(kind))
    names = {bool: "true or false", int: "an integer", float: "a number", str: "text",
             type(None): "null", dict: "a JSON object"}
    return names.get(typing.get_origin(kind) or kind, str(kind))


def parse_options(options_type: type[PolicyOptions], args: Mapping[str, Any], policy: str
                  ) -> PolicyOptions:
    """`options_type` filled from `args` (--policy-arg pairs, values parsed as JSON where
    they could be); an OptionsError in one line for an unknown key (naming the valid ones)
    or a value of the wrong type."""
    known = [f.name for f in fields(options_type)]
    unknown = [k for k in args if k not in known]
    if unknown:
        valid = ", ".join(known) if known else "none"
        raise OptionsError(f"--policy {policy} takes no --policy-arg {', '.join(unknown)}; "
                           f"its options: {valid} (--policy-arg help describes them)")
    try:
        return options_type(**args)
    except OptionsError as e:
        raise OptionsError(f"--policy {policy}: --policy-arg {e}") from None


def describe(options_type: type[PolicyOptions], policy: str) -> str:
    """The options of `policy` for the terminal: KEY=DEFAULT and its help, one per line."""
    hints = typing.get_type_hints(options_type)
    rows = []
    for f in fields(options_type):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        try:
            shown = json.dumps(default)
        except TypeError:  # a sentinel: its repr says what it stands for
            shown = repr(default)
        rows.append(f"  {f.name}={shown}  ({_expected(hints[f.name])}) "
                    f"{f.metadata['help']}")
    head = f"--policy {policy} options (--policy-arg KEY=VALUE, VALUE as JSON where it parses):"
    return "\n".join([head, *rows] if rows else [head, "  none"])

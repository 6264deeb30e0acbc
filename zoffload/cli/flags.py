"""Command-line flags built from the settings models, so that a setting is declared once.

Every field of a settings model is a flag named after its YAML key path, dashes for underscores:
``voxel`` is ``--voxel``, ``perception.cpu_max`` is ``--perception.cpu-max``. The field gives the
rest: its ``description`` is the help, its default is shown, and its annotation sets the form:

* ``Literal[...]``: one of the choices;   ``int`` / ``float`` / ``str``: one value of that type;
* ``bool``: ``--x`` / ``--no-x`` (``--section.x`` / ``--section.no-x``);
* ``tuple[float, float]``: two values;    ``list[str]``: repeat the flag, one item each;
* ``X | None``: as ``X``;                 a nested model: a group of its own flags.

A program's table of :class:`Spelling` (by key path) only renames flags that have had other
spellings for long, such as ``-e/--connect`` for ``zenoh.connect``. A flag not given stays out of
:func:`flag_values`, so it never overrides the YAML file or the environment.
"""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from zoffload.runtime.loading import section_model, unwrap_optional

_SCALARS = (int, float, str)
_METAVARS = {int: "INT", float: "FLOAT", str: "TEXT"}


@dataclass(frozen=True)
class Spelling:
    """A setting's flag when it is not the derived ``--key-name``: its option strings (for a
    bool, the "on" forms: the ``--no-`` forms are derived) and, optionally, its metavar."""

    options: tuple[str, ...]
    metavar: str | tuple[str, ...] | None = None


def option_name(path: str) -> str:
    """The derived flag of a key path: ``perception.cpu_max`` → ``--perception.cpu-max``."""
    return "--" + path.replace("_", "-")


def _negative(option: str) -> str:
    section, _, name = option[2:].rpartition(".")
    return f"--{section}.no-{name}" if section else f"--no-{name}"


class _Switch(argparse.Action):
    """``--x`` stores True, ``--no-x`` False; like argparse's BooleanOptionalAction, but with the
    ``no-`` after the section (``--mapper.no-deskew``) and renamed on-flags (``--shm``)."""

    def __init__(self, option_strings: Sequence[str], dest: str, off: Sequence[str] = (),
                 default: Any = None, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)
        self.off = frozenset(off)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        setattr(namespace, self.dest, option_string not in self.off)

    def format_usage(self) -> str:
        return " | ".join(self.option_strings)


def _shown_default(value: Any) -> str | None:
    if value is None or value == []:
        return None  # the description says what "unset" means
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value)  # as it would be typed after the flag
    return str(value)


def _help(field: FieldInfo) -> str:
    text = field.description or ""
    shown = _shown_default(field.get_default(call_default_factory=True))
    if shown is not None:
        text = f"{text} (default: {shown})" if text else f"default: {shown}"
    return text.replace("%", "%%")  # argparse %-formats help strings


def _value_form(path: str, annotation: Any) -> dict[str, Any]:
    """``add_argument`` keywords for a value that is not a bool: type, and choices, nargs or action."""
    kind = unwrap_optional(annotation)
    origin, args = get_origin(kind), get_args(kind)
    if origin is Literal:
        return {"type": type(args[0]), "choices": args}
    if kind in _SCALARS:
        return {"type": kind}
    if origin is list and len(args) == 1 and args[0] in _SCALARS:
        return {"type": args[0], "action": "append"}
    if origin is tuple and args and Ellipsis not in args and len(set(args)) == 1 and args[0] in _SCALARS:
        return {"type": args[0], "nargs": len(args)}
    raise TypeError(f"setting {path}: no command-line form for {annotation!r} (see zoffload.cli.flags)")


def _add_flag(group: argparse._ArgumentGroup, path: str, field: FieldInfo,
              spelling: Spelling | None) -> None:
    options = spelling.options if spelling else (option_name(path),)
    if unwrap_optional(field.annotation) is bool:
        off = tuple(_negative(o) for o in options if o.startswith("--"))
        group.add_argument(*options, *off, dest=path, action=_Switch, off=off, default=None,
                           help=_help(field))
        return
    form = _value_form(path, field.annotation)
    metavar = spelling.metavar if spelling and spelling.metavar else None
    if metavar is None and "choices" not in form:  # argparse shows the choices themselves
        kind = _METAVARS[form["type"]]
        metavar = (kind,) * form["nargs"] if "nargs" in form else kind
    group.add_argument(*options, dest=path, default=None, metavar=metavar, help=_help(field), **form)


def summary(model: type[BaseModel]) -> str | None:
    """The first paragraph of a model's docstring, on one line."""
    doc = inspect.getdoc(model)
    return " ".join(doc.split("\n\n")[0].split()) if doc else None


def add_settings_flags(
    parser: argparse.ArgumentParser,
    model: type[BaseModel],
    spellings: Mapping[str, Spelling] | None = None,
    prefix: str = "",
    title: str | None = None,
) -> None:
    """One flag per field of ``model`` (``prefix``: its key path inside the program's settings),
    in a group per section, each section's group described by its model's docstring;
    ``spellings`` renames some, by key path."""
    spellings = spellings or {}
    used: set[str] = set()

    def add(model: type[BaseModel], prefix: str, title: str, description: str | None) -> None:
        group = parser.add_argument_group(title, description)
        sections: list[tuple[str, type[BaseModel]]] = []
        for name, field in model.model_fields.items():
            path = f"{prefix}.{name}" if prefix else name
            section = section_model(field)
            if section is not None:
                sections.append((path, section))  # after this model's own flags
            else:
                _add_flag(group, path, field, spellings.get(path))
                used.add(path)
        for path, section in sections:
            add(section, path, path, summary(section))

    # The program's own model describes the parser itself, not a group.
    add(model, prefix, title or prefix or "settings", summary(model) if prefix else None)
    unknown = sorted(set(spellings) - used)
    if unknown:  # a renamed setting that no longer exists: the table is out of date
        raise KeyError(f"flag spellings name settings {model.__name__} does not have: {', '.join(unknown)}")


def flag_values(args: argparse.Namespace, model: type[BaseModel], prefix: str = "") -> dict[str, Any]:
    """The settings given as flags, nested like the YAML file; flags not given are left out."""
    out: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        path = f"{prefix}.{name}" if prefix else name
        section = section_model(field)
        if section is not None:
            inner = flag_values(args, section, path)
            if inner:
                out[name] = inner
            continue
        value = getattr(args, path, None)
        if value is not None:
            out[name] = value
    return out

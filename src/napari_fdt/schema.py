"""The settings schema: how a setting is declared once and read by every front end.

A settings class is a pydantic dataclass built by :func:`schema_dataclass` (unknown keys refused, infinities
and NaN refused) whose fields are declared with :func:`setting` (a description, bounds such as ``ge``/``gt``,
``Literal[...]`` choices and an optional ``fix`` hint). Building one with bad values raises
:class:`~napari_fdt.errors.FDTInputError` — the one-line ``field: problem (fix)`` message — through the single
adapter :func:`input_error`. The command line, the napari widgets and the documentation's settings tables read
the same fields through :func:`schema_fields`, :func:`bounds`, :func:`choices` and :func:`markdown_table`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import types
import typing
from typing import Any, Callable, Literal, TypeVar, Union

import annotated_types
from pydantic import ConfigDict, Field, ValidationError
from pydantic.dataclasses import dataclass as pydantic_dataclass
from pydantic.fields import FieldInfo

from napari_fdt.errors import FDTInputError

__all__ = [
    "SCHEMA_CONFIG",
    "accepts_auto",
    "number_words",
    "bounds",
    "choices",
    "example",
    "input_error",
    "markdown_table",
    "TIERS",
    "tier",
    "scalar_type",
    "schema_dataclass",
    "schema_fields",
    "setting",
]

T = TypeVar("T")

#: Model configuration of every settings class: unknown keys and non-finite numbers are refused.
SCHEMA_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False)


#: The tiers of settings, in the order ``--help`` and the docs show them: the few a user sets, the advanced ones, and
#: the experimental ones (kept while they are measured; docs/settings.md).
TIERS = ("basic", "advanced", "experimental")


def setting(default: Any = dataclasses.MISSING, *, description: str, fix: str = "", example: Any = None,
            default_factory: Callable[[], Any] | None = None, strict: bool = True, tier: str = "advanced",
            **constraints: Any) -> Any:
    """A settings field: ``description`` (shown in docs, ``--help`` and tooltips), bounds (``ge``, ``gt``, ``le``,
    ``lt``), ``fix``, the hint appended to its error messages, ``example``, a typical value for a required
    field (prefilled in forms), and ``tier`` (:data:`TIERS`). Strict: no strings for numbers, no booleans for numbers,
    no fractional values for integers."""
    if tier not in TIERS:
        raise ValueError(f"tier must be one of {TIERS}, got {tier!r}")
    extra = {k: v for k, v in (("fix", fix), ("example", example)) if v not in ("", None)}
    if tier != "advanced":
        extra["tier"] = tier
    extra = extra or None
    kwargs: dict[str, Any] = dict(description=description, json_schema_extra=extra, **constraints)
    if strict:
        kwargs["strict"] = True
    if default_factory is not None:
        return Field(default_factory=default_factory, **kwargs)
    if default is dataclasses.MISSING:
        return Field(**kwargs)
    return Field(default, **kwargs)


def schema_dataclass(cls: type[T] | None = None, *, frozen: bool = False, root: str = "config", prefix: str = "") -> Any:
    """Make ``cls`` a validated settings dataclass whose constructor raises :class:`FDTInputError`.

    ``root`` names the object in errors about unknown keys (``"config.learning_rate"``); ``prefix`` goes before
    the field names in errors when the class is built directly (``"stages[]."`` for a stage). The class stays a
    dataclass: ``dataclasses.asdict``, ``fields`` and ``replace`` (which validates again) work on it.
    """

    def wrap(klass: type[T]) -> type[T]:
        built = pydantic_dataclass(klass, config=SCHEMA_CONFIG, frozen=frozen)
        validating_init = built.__init__

        @functools.wraps(validating_init)
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            try:
                validating_init(self, *args, **kwargs)
            except ValidationError as exc:
                raise input_error(exc, built, root, prefix) from None

        built.__init__ = __init__
        built.__schema_root__ = root
        return built

    return wrap if cls is None else wrap(cls)


def tier(info: FieldInfo) -> str:
    """The field's tier (:data:`TIERS`; "advanced" unless set)."""
    extra = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
    return str(extra.get("tier", "advanced"))


def schema_fields(model: type) -> dict[str, FieldInfo]:
    """The fields of a settings class, in declaration order."""
    return dict(model.__pydantic_fields__)


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and hasattr(tp, "__pydantic_fields__")


def _inner_model(annotation: Any) -> type | None:
    """The settings class nested in ``annotation`` (``list[StageConfig]`` → ``StageConfig``), if any."""
    if _is_model(annotation):
        return annotation
    for arg in typing.get_args(annotation):
        found = _inner_model(arg)
        if found is not None:
            return found
    return None


def number_words(info: FieldInfo) -> tuple[str, ...]:
    """The words a numeric field also takes (``("auto",)`` for ``sub_slices``; ``field_oversampling`` takes
    ``"before_spectral"`` too), else ``()``."""
    annotation = info.annotation
    if typing.get_origin(annotation) not in (Union, types.UnionType):
        return ()
    args = typing.get_args(annotation)
    if all(typing.get_origin(a) is Literal or a is type(None) for a in args):
        return ()
    return tuple(w for a in args if typing.get_origin(a) is Literal for w in typing.get_args(a))


def accepts_auto(info: FieldInfo) -> bool:
    """Whether a numeric field also takes the string ``"auto"`` (a value chosen from the data)."""
    return "auto" in number_words(info)


def scalar_type(info: FieldInfo) -> tuple[type | None, bool]:
    """``(type, optional)`` of a scalar field: ``bool``, ``int``, ``float`` or ``str`` (a ``Literal``), and whether
    None is allowed; ``(None, …)`` for other fields (lists, nested settings). A number that also takes ``"auto"``
    (:func:`accepts_auto`) is reported as its numeric type."""
    annotation = info.annotation
    optional = False
    if typing.get_origin(annotation) in (Union, types.UnionType):
        optional = type(None) in typing.get_args(annotation)
        args = [a for a in typing.get_args(annotation) if a is not type(None)
                and not (typing.get_origin(a) is Literal and number_words(info))]
        if len(args) != 1:
            return None, optional
        annotation = args[0]
    if typing.get_origin(annotation) is typing.Annotated:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) is Literal:
        return str, optional
    if annotation in (bool, int, float, str):
        return annotation, optional
    return None, optional


def _constraints(info: FieldInfo) -> list[Any]:
    """Constraint objects of a field, including those of an ``Annotated`` member of an optional type."""
    found = list(info.metadata)
    for arg in typing.get_args(info.annotation):
        if typing.get_origin(arg) is typing.Annotated:
            for meta in typing.get_args(arg)[1:]:
                found.extend(meta.metadata if isinstance(meta, FieldInfo) else [meta])
    return found


def bounds(info: FieldInfo) -> dict[str, float]:
    """The numeric bounds of a field: a subset of ``{"ge", "gt", "le", "lt"}``."""
    out: dict[str, float] = {}
    for meta in _constraints(info):
        for key, kind in (("ge", annotated_types.Ge), ("gt", annotated_types.Gt), ("le", annotated_types.Le), ("lt", annotated_types.Lt)):
            if isinstance(meta, kind):
                out[key] = getattr(meta, key)
    return out


def choices(info: FieldInfo) -> tuple[str, ...] | None:
    """The allowed values of a ``Literal`` field, else None."""
    annotation = info.annotation
    if typing.get_origin(annotation) is Literal:
        return tuple(typing.get_args(annotation))
    return None


def example(info: FieldInfo) -> Any:
    """The field's example value, else its default (None when it has neither)."""
    extra = info.json_schema_extra
    if isinstance(extra, dict) and "example" in extra:
        return extra["example"]
    return None if info.is_required() else info.get_default(call_default_factory=True)


def _fix_of(info: FieldInfo | None) -> str:
    extra = info.json_schema_extra if info is not None else None
    return str(extra.get("fix", "")) if isinstance(extra, dict) else ""


def _type_fix(error: dict[str, Any]) -> str:
    """The default hint for one kind of pydantic error."""
    kind, ctx = error["type"], error.get("ctx") or {}
    if kind in ("greater_than_equal", "greater_than", "less_than_equal", "less_than"):
        sign = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}[kind]
        key = {"greater_than_equal": "ge", "greater_than": "gt", "less_than_equal": "le", "less_than": "lt"}[kind]
        return f"give a value {sign} {ctx.get(key):g}"
    if kind == "literal_error":
        return f"choose one of {ctx.get('expected')}"
    return {
        "finite_number": "write a finite number",
        "int_type": "write a whole number",
        "int_from_float": "write a whole number",
        "float_type": "write a plain number",
        "bool_type": "write true or false",
        "string_type": "write a string",
        "list_type": "write a list",
        "missing_argument": "add it",
        "missing": "add it",
    }.get(kind, "")


def input_error(exc: ValidationError, model: type, root: str = "config", prefix: str = "") -> FDTInputError:
    """The one :class:`FDTInputError` for a pydantic ``ValidationError`` raised while building ``model``.

    The first error is reported. Its field is the dotted location with list indices written ``[]``
    (``stages[].factor``); an unknown key is named under ``root`` (``config.learning_rate``). An
    ``FDTInputError`` raised by a cross-field validator passes through unchanged; ``prefix`` goes before other
    field names. The fix is the field's own ``fix``, else a hint for the kind of error.
    """
    error = exc.errors(include_url=False)[0]
    cause = (error.get("ctx") or {}).get("error")
    if isinstance(cause, FDTInputError):
        return cause
    # Walk the location: name each part, keep the field and the settings class that owns the last name.
    name, owner, info = "", model, None
    for i, part in enumerate(error["loc"]):
        if isinstance(part, int) and i == 0:  # a positional argument of the constructor
            part = list(schema_fields(model))[part] if part < len(schema_fields(model)) else "[]"
        if isinstance(part, int):
            name += "[]"
            continue
        fields = schema_fields(owner) if owner is not None else {}
        if part not in fields and info is not None and owner is None:
            continue  # the tag of a union's member ("constrained-float" of a number-or-"auto" field)
        info = fields.get(part)
        name = f"{name}.{part}" if name else str(part)
        owner = _inner_model(info.annotation) if info is not None else None
    kind = error["type"]
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        parent = name.rpartition(".")[0] if "." in name else root
        parent_model = model if parent == root else _owner_of(model, parent)
        known = ", ".join(schema_fields(parent_model)) if parent_model is not None else ""
        return FDTInputError(f"{parent}.{name.rpartition('.')[2]}", "is not a setting", f"known settings: {known}")
    name = prefix + name if name else root
    problem = _problem(error)
    fix = _fix_of(info) or _type_fix(error)
    return FDTInputError(name, problem, fix)


def _problem(error: dict[str, Any]) -> str:
    """``must be …, got …`` for one pydantic error (a number out of bounds written with ``:g``)."""
    kind, ctx = error["type"], error.get("ctx") or {}
    if kind in ("missing", "missing_argument"):
        return "is missing"
    if kind == "greater_than":
        text = "must be positive" if ctx.get("gt") == 0 else f"must be > {ctx.get('gt'):g}"
    elif kind in ("greater_than_equal", "less_than_equal", "less_than"):
        sign, key = {"greater_than_equal": (">=", "ge"), "less_than_equal": ("<=", "le"), "less_than": ("<", "lt")}[kind]
        text = f"must be {sign} {ctx.get(key):g}"
    else:
        msg = error["msg"]
        text = "must be" + msg[len("Input should be"):] if msg.startswith("Input should be") else msg[:1].lower() + msg[1:]
    value = error.get("input")
    bound = kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal")
    shown = f"{value:g}" if bound and isinstance(value, float) else _short(value)
    return f"{text}, got {shown}"


def _owner_of(model: type, dotted: str) -> type | None:
    owner: type | None = model
    for part in dotted.replace("[]", "").split("."):
        info = schema_fields(owner).get(part) if owner is not None else None
        owner = _inner_model(info.annotation) if info is not None else None
    return owner


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _markdown_value(value: Any) -> str:
    if value is None:
        return "null"
    if dataclasses.is_dataclass(value) or isinstance(value, list):
        value = json.loads(json.dumps(value, default=dataclasses.asdict))
    return f"`{json.dumps(value)}`" if not isinstance(value, (int, float)) or isinstance(value, bool) else repr(value)


def _markdown_type(info: FieldInfo) -> str:
    kind, optional = scalar_type(info)
    options = choices(info)
    auto = "".join(f' or `"{w}"`' for w in number_words(info))
    if options is not None:
        text = " \\| ".join(f'`"{c}"`' for c in options)
    elif kind is not None:
        text = {bool: "bool", int: "int", float: "float", str: "str"}[kind]
        limits = bounds(info)
        signs = {"ge": "≥", "gt": ">", "le": "≤", "lt": "<"}
        if limits:
            text += " " + ", ".join(f"{signs[k]} {v:g}" for k, v in limits.items())
    else:
        inner = _inner_model(info.annotation)
        text = f"list of {inner.__name__}" if inner is not None else str(info.annotation)
    return text + auto + (" or null" if optional else "")


def markdown_table(model: type) -> str:
    """The Markdown table of a settings class: one row per field with its type and bounds, default and meaning."""
    rows = ["| setting | tier | type | default | meaning |", "|---|---|---|---|---|"]
    fields = schema_fields(model)
    for name, info in sorted(fields.items(), key=lambda kv: TIERS.index(tier(kv[1]))):  # stable: declaration order within a tier
        default = info.get_default(call_default_factory=True)
        meaning = (info.description or "").replace("|", "\\|")
        rows.append(f"| `{name}` | {tier(info)} | {_markdown_type(info)} | {_markdown_value(default)} | {meaning} |")
    return "\n".join(rows) + "\n"

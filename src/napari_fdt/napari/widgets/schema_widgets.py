"""magicgui widgets generated from the settings schema (:mod:`napari_fdt.schema`), as waveorder builds its forms.

One widget per field: a ``CheckBox`` for a bool, a ``ComboBox`` with the ``Literal``'s choices, a ``SpinBox`` or
``FloatSpinBox`` with the field's bounds and default; the tooltip is the field's description. The widget's
name is the field's, so a form's values map straight back onto the settings class.
"""

from __future__ import annotations

from typing import Any

from magicgui.widgets import CheckBox, ComboBox, Container, FloatSpinBox, SpinBox, Widget

from napari_fdt.schema import accepts_auto, bounds, choices, example, scalar_type, schema_fields

__all__ = ["schema_widget", "AutoNumber", "WIDE_LIMIT"]

#: Range of a spin box whose field has no bound on that side (and of every spin box with ``clamp=False``).
WIDE_LIMIT = 1e6


def _limits(info, kind: type, clamp: bool) -> tuple[float, float]:
    """(min, max) of a spin box: the field's bounds (``gt``/``lt`` of an int moved inward by one); without
    ``clamp`` only the sign of a lower bound is kept, so that the core, not the spin box, refuses a value."""
    b = bounds(info)
    lower = b.get("ge", b.get("gt"))
    upper = b.get("le", b.get("lt"))
    if not clamp:
        return (0.0 if lower is not None and lower >= 0 else -WIDE_LIMIT), WIDE_LIMIT
    if kind is int:
        lo = b["ge"] if "ge" in b else (b["gt"] + 1 if "gt" in b else -(2**31))
        hi = b["le"] if "le" in b else (b["lt"] - 1 if "lt" in b else 2**31 - 1)
        return lo, hi
    return (-WIDE_LIMIT if lower is None else lower), (WIDE_LIMIT if upper is None else upper)


class AutoNumber(Container):
    """A number that may also be ``"auto"`` (chosen from the data): an *auto* check box beside a spin box, which is
    disabled while *auto* is ticked. ``value`` is ``"auto"`` or the number; it accepts either."""

    def __init__(self, spin: FloatSpinBox | SpinBox, *, name: str, label: str, value: Any, tooltip: str) -> None:
        self.auto = CheckBox(text="auto", value=value == "auto", tooltip="chosen from the data by the validation error")
        self.number = spin
        super().__init__(widgets=[self.auto, self.number], layout="horizontal", labels=False, name=name, label=label,
                         tooltip=tooltip)
        self.margins = (0, 0, 0, 0)
        self.number.enabled = not self.auto.value
        self.auto.changed.connect(lambda checked: setattr(self.number, "enabled", not checked))

    @property
    def value(self) -> Any:
        return "auto" if self.auto.value else self.number.value

    @value.setter
    def value(self, value: Any) -> None:
        if value == "auto":
            self.auto.value = True
        else:
            self.auto.value = False
            self.number.value = value


def schema_widget(model: type, name: str, *, label: str | None = None, value: Any = None, step: float | None = None,
                  clamp: bool = True) -> Widget:
    """The magicgui widget of field ``name`` of settings class ``model``.

    ``label`` defaults to the field name with spaces; ``value`` to the field's default (or example value);
    ``step`` is the float spin box's increment. With ``clamp`` False the spin box accepts out-of-bounds values
    (zero, negative where the field allows it) and leaves the refusal, with its message, to the core.
    """
    info = schema_fields(model)[name]
    kind, _ = scalar_type(info)
    label = label or name.replace("_", " ")
    value = example(info) if value is None else value
    tooltip = (info.description or "").replace("`", "")
    options = choices(info)
    if kind is bool:
        return CheckBox(name=name, text=label, value=value, tooltip=tooltip)
    if options is not None:
        return ComboBox(name=name, label=label, choices=list(options), value=value, tooltip=tooltip)
    if kind is int:
        lo, hi = _limits(info, int, clamp)
        if accepts_auto(info):  # a whole number or "auto" (sub_slices)
            spin = SpinBox(name=name + "_number", value=int(lo) if value == "auto" else value, min=int(lo), max=int(hi), tooltip=tooltip)
            return AutoNumber(spin, name=name, label=label, value=value, tooltip=tooltip)
        return SpinBox(name=name, label=label, value=value, min=int(lo), max=int(hi), tooltip=tooltip)
    if kind is float:
        lo, hi = _limits(info, float, clamp)
        extra = {} if step is None else {"step": step}
        if accepts_auto(info):
            spin = FloatSpinBox(name=name + "_number", value=0.0 if value == "auto" else value, min=lo, max=hi, tooltip=tooltip, **extra)
            return AutoNumber(spin, name=name, label=label, value=value, tooltip=tooltip)
        return FloatSpinBox(name=name, label=label, value=value, min=lo, max=hi, tooltip=tooltip, **extra)
    raise TypeError(f"{model.__name__}.{name} is not a scalar setting; build its widget by hand")

"""Declarative input schemas: what a key holds, and the reader and checks derived from it.

A `Key` states one input key once: its kind, unit, default, allowed range or choices and
meaning. A `Section` is a table of keys, optionally with keys that exist only for one value of
a discriminating key (a probe's `kind`, a material's `model`). From these declarations come
- `read_section`: a TOML table (nested dicts) to checked, converted Python values;
- `check_value`: the same range and choice checks on values built in Python;
- `describe`: the rows of the generated reference (docs/scene_reference.md).
Every error is a `SceneError` of one sentence naming the key's full path and the bad value.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from typing import Any

import jax

from jaxmpm.errors import SceneError

REQUIRED = object()          # the default of a key that must be given
PLAIN = re.compile(r"^[A-Za-z0-9_\-]+$")

# kind -> how the reference describes a value of that kind
KINDS = {
    "float": "number",
    "int": "integer",
    "str": "string",
    "vec2": "[x, y]",
    "points": "[[x, y], ...]",
    "vec2_or_points": "[x, y] or [[x, y], ...]",
    "floats": "[number, ...]",
    "strings": "[string, ...]",
    "table": "table",
    "tables": "array of tables",
    "named_tables": "table of named tables",
    "mapping": "table of NAME = value",
}


@dataclasses.dataclass(frozen=True)
class Key:
    """One input key.

    kind: one of KINDS. default: REQUIRED, a value, or None (absent means "not given": the
    meaning says what happens then). low/high: bounds of a number, or of each number of a
    vector (`low_inclusive`/`high_inclusive` say whether the bound itself is allowed).
    choices: the allowed strings (or, for "strings", the allowed items); `words`: strings a
    number key also accepts (k0 = "jaky"). length: the exact number of items of a list.
    section: the keys of a "table", "tables" or "named_tables" entry. A "mapping" is a table
    whose names are the user's (probe names, parameter names): its values are checked by the
    code that uses them.
    """

    name: str
    kind: str
    meaning: str
    unit: str = ""
    default: Any = REQUIRED
    low: float | None = None
    high: float | None = None
    low_inclusive: bool = False
    high_inclusive: bool = False
    choices: tuple | None = None
    words: tuple = ()
    length: int | None = None
    section: Section | None = None

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @property
    def range_text(self) -> str:
        """The allowed values, as the reference and the messages write them."""
        if self.choices is not None:
            return ", ".join(repr(choice) for choice in self.choices)
        if self.low is None and self.high is None:
            return ""
        left = "[" if self.low_inclusive else "("
        right = "]" if self.high_inclusive else ")"
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        span = f"{left}{low}, {high}{right}"
        return " or ".join([span, *map(repr, self.words)])


@dataclasses.dataclass(frozen=True)
class Section:
    """A table's keys. `variant_key` names a key whose value selects extra keys from
    `variants` (value -> keys): a probe's kind, a material's model. `one_of`: exactly one of
    the keys is given (a region is a rectangle or a polygon)."""

    keys: tuple[Key, ...]
    meaning: str = ""
    variant_key: str | None = None
    variants: dict | None = None
    one_of: bool = False

    def keys_for(self, variant=None) -> tuple[Key, ...]:
        """The keys of the table when its variant key has the value `variant`."""
        return self.keys + tuple((self.variants or {}).get(variant, ()))

    def all_names(self) -> list[str]:
        names = [key.name for key in self.keys]
        for keys in (self.variants or {}).values():
            names += [key.name for key in keys if key.name not in names]
        return names

    def key(self, name, variant=None) -> Key:
        return next(key for key in self.keys_for(variant) if key.name == name)


# --------------------------------------------------------------------------- values


def is_concrete(value) -> bool:
    """True for Python/numpy numbers; False for JAX tracers (which cannot be range-checked)."""
    return not isinstance(value, jax.core.Tracer)


def number(path, value):
    """A finite float from a TOML number (tracers pass through unchecked)."""
    if not is_concrete(value):          # a JAX value being differentiated (e.g. in `drive`)
        return value
    if hasattr(value, "dtype") and getattr(value, "shape", None) == ():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"{path} = {value!r} must be a number.")
    if not math.isfinite(value):
        raise SceneError(f"{path} = {value!r} must be finite.")
    return float(value)


def check_range(path, value, low=None, high=None, low_inclusive=False, high_inclusive=False):
    """SceneError unless low < value < high (bounds optional, inclusivity as given)."""
    if not is_concrete(value):
        return
    value = number(path, value)
    too_low = low is not None and (value < low if low_inclusive else value <= low)
    too_high = high is not None and (value > high if high_inclusive else value >= high)
    if too_low or too_high:
        span = Key("", "float", "", low=low, high=high, low_inclusive=low_inclusive,
                   high_inclusive=high_inclusive).range_text
        raise SceneError(f"{path} = {value!r} is out of range: it must lie in {span}.")


def _pair(path, value):
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SceneError(f"{path} = {_shown(value)} must be a pair of numbers [x, y].")
    return tuple(number(path, item) for item in value)


def _shown(value):
    """A value as the scene file wrote it (tuples as lists)."""
    if isinstance(value, tuple):
        return repr([list(item) if isinstance(item, tuple) else item for item in value])
    return repr(value)


def convert(path, value, kind):
    """Check a TOML value against `kind` and convert it (ints to floats where a float is due,
    lists to tuples)."""
    if kind == "float":
        return number(path, value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{path} = {value!r} must be an integer.")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise SceneError(f"{path} = {value!r} must be a string.")
        return value
    if kind == "strings":
        if not isinstance(value, (list, tuple)) or not all(isinstance(item, str) for item in value):
            raise SceneError(f"{path} = {value!r} must be a list of strings.")
        return tuple(value)
    if kind == "floats":
        if not isinstance(value, (list, tuple)) or not value:
            raise SceneError(f"{path} = {value!r} must be a list of numbers.")
        return tuple(number(path, item) for item in value)
    if kind == "vec2":
        return _pair(path, value)
    if kind == "points":
        if not isinstance(value, (list, tuple)) or not value:
            raise SceneError(f"{path} = {value!r} must be a list of points [[x, y], ...].")
        return tuple(_pair(path, item) for item in value)
    if kind == "vec2_or_points":
        if isinstance(value, (list, tuple)) and value and isinstance(value[0], (list, tuple)):
            return convert(path, value, "points")
        return _pair(path, value)
    raise AssertionError(kind)


def check_value(path, key: Key, value):
    """The type, range and choice checks of `key` on a value (None passes when the key may be
    absent). Used on what the reader read and on dataclasses built in Python."""
    if value is None:
        if key.required:
            raise SceneError(f"{path} is missing: it is required.")
        return
    if key.words and isinstance(value, str):
        if value not in key.words:
            raise SceneError(f"{path} = {value!r} must be a number or one of {', '.join(map(repr, key.words))}.")
        return
    if key.section is None:
        value = convert(path, value, key.kind)
    if key.choices is not None:
        items = value if key.kind == "strings" else (value,)
        for item in items:
            if item not in key.choices:
                where = f"{path} has {item!r}, which" if key.kind == "strings" else f"{path} = {item!r}"
                raise SceneError(f"{where} is not one of {key.range_text}.")
    if key.length is not None and len(value) != key.length:
        raise SceneError(f"{path} = {_shown(value)} must have {key.length} items.")
    if key.low is None and key.high is None:
        return
    bounds = (key.low, key.high, key.low_inclusive, key.high_inclusive)
    if key.kind in ("vec2", "floats"):
        for index, item in enumerate(value):
            check_range(f"{path}[{index}]", item, *bounds)
    else:
        check_range(path, value, *bounds)


# --------------------------------------------------------------------------- reading


def _unknown_key_error(path, name, known, missing):
    """One sentence for a key the section does not have, with the closest known key."""
    close = difflib.get_close_matches(name, known, n=1)
    if not close:
        return SceneError(f"{_join(path, name)} is not a known key.")
    if close[0] in missing:
        return SceneError(
            f"{_join(path, name)} is not a known key (did you mean {close[0]!r}? "
            f"{_join(path, close[0])} is required and missing)."
        )
    return SceneError(f"{_join(path, name)} is not a known key (did you mean {close[0]!r}?).")


def _join(path, name):
    """A key's full path; a name that is not plain letters, digits, '_' or '-' is quoted."""
    shown = name if PLAIN.match(name) else repr(name)
    return f"{path}.{shown}" if path else shown


def read_section(section: Section, data, path: str) -> dict:
    """The checked values of a TOML table {name: value}, defaults filled in. Unknown keys are
    refused first (with the closest known key), then missing required ones."""
    if not isinstance(data, dict):
        raise SceneError(f"{path} = {data!r} must be a table.")
    variant = None
    if section.variant_key is not None:
        spec = section.key(section.variant_key)
        if section.variant_key in data:
            variant = read_value(spec, data[section.variant_key], _join(path, section.variant_key))
        elif not spec.required:
            variant = spec.default
    keys = section.keys_for(variant)
    names = [key.name for key in keys]
    missing = [key.name for key in keys if key.required and key.name not in data]
    for name in data:
        if name in names:
            continue
        if name in section.all_names():
            if variant is None:         # the variant key is missing: that is the error
                continue
            raise SceneError(
                f"{_join(path, name)} does not apply when {section.variant_key} = {variant!r}: remove it."
            )
        raise _unknown_key_error(path, name, names, missing)
    if section.one_of and len(data) != 1:
        options = " or ".join(f"{key.name} = {KINDS[key.kind]}" for key in keys)
        raise SceneError(f"{path} = {data!r} must hold exactly one of {options}.")
    if missing and not section.one_of:
        raise SceneError(f"{_join(path, missing[0])} is missing: it is required.")
    return {key.name: read_value(key, data[key.name], _join(path, key.name)) if key.name in data else _absent(key, path)
            for key in keys if key.name in data or not section.one_of}


def _absent(key: Key, path):
    """The value of a key that is not given: its default (an optional table read empty)."""
    if key.kind == "table" and isinstance(key.default, dict):
        return read_section(key.section, key.default, _join(path, key.name))
    return key.default


def read_value(key: Key, value, path: str):
    """One key's checked value (nested tables read by their sections)."""
    if key.kind == "table":
        return read_section(key.section, value, path)
    if key.kind == "tables":
        if not isinstance(value, list):
            raise SceneError(f"{path} must be an array of tables ([[{path}]]).")
        return [read_section(key.section, entry, f"{path}[{index}]") for index, entry in enumerate(value)]
    if key.kind == "named_tables":
        if not isinstance(value, dict):
            raise SceneError(f"{path} = {value!r} must be a table of named tables ([{path}.NAME]).")
        return {name: read_section(key.section, entry, f"{path}.{name}") for name, entry in value.items()}
    if key.kind == "mapping":
        if not isinstance(value, dict):
            raise SceneError(f"{path} = {value!r} must be a table of NAME = value.")
        return dict(value)
    if key.words and isinstance(value, str):
        check_value(path, key, value)
        return value
    value = convert(path, value, key.kind)
    check_value(path, key, value)
    return value


# --------------------------------------------------------------------------- reference


def _default_text(key: Key) -> str:
    if key.required:
        return "required"
    if key.default is None:
        return "—"
    if key.section is not None:
        if not key.default:
            return "optional"
        return "`" + ", ".join(f'{name} = "{value}"' for name, value in key.default.items()) + "`"
    if isinstance(key.default, tuple):
        return "`" + repr(list(key.default)).replace("'", '"') + "`"
    if isinstance(key.default, str):
        return f'`"{key.default}"`'
    return f"`{key.default!r}`"


def _kind_text(key: Key) -> str:
    kind = KINDS[key.kind]
    if key.words:
        kind += " or " + " or ".join(f'"{word}"' for word in key.words)
    if key.length is not None:
        kind += f" ({key.length} items)"
    return kind


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + "."


def _presence(key: Key) -> str:
    if key.required:
        return "Required."
    if key.default is None or not key.default:
        return "Optional."
    return f"Default: {_default_text(key)}."


def reference_tables(section: Section, title: str, path: str, level: int = 2, note: str = "") -> list[str]:
    """Markdown lines for a section: a heading, a table of its value keys (kind, unit,
    default, allowed values, meaning), each variant's keys, then its nested tables."""
    lines = [f"{'#' * level} `{title}`", ""]
    if section.meaning or note:
        lines += [" ".join(filter(None, [_sentence(section.meaning) if section.meaning else "", note])), ""]
    nested = []
    for variant, keys in [(None, section.keys)] + list((section.variants or {}).items()):
        values = [key for key in keys if key.section is None]
        if variant is not None:
            lines += [f'With `{section.variant_key} = "{variant}"`' + (":" if values else ": no further keys."), ""]
        if values:
            lines += ["| key | kind | unit | default | allowed | meaning |", "|---|---|---|---|---|---|"]
            lines += [f"| `{key.name}` | {_cell(_kind_text(key))} | {key.unit or '–'} | {_cell(_default_text(key))} "
                      f"| {_cell(key.range_text) or 'any'} | {_cell(key.meaning)} |" for key in values]
            lines.append("")
        nested += [key for key in keys if key.section is not None]
    for key in nested:
        name = _join(path, key.name)
        title, inner = {"tables": (f"[[{name}]]", f"{name}[i]"),
                        "named_tables": (f"[{name}.NAME]", f"{name}.NAME")}.get(key.kind, (f"[{name}]", name))
        lines += reference_tables(key.section, title, inner, level + 1 if path else level, _presence(key))
    return lines

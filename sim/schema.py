"""The one home of "a value a user wrote is checked, in one line": pydantic settings and messages.

Every user-written file (a train config TOML and a run's ``config.json``, an exported model's
``manifest.json``, a cell YAML, a sweep's ``sweep.json``) has a typed schema in the module that owns
the file; they all validate with :data:`STRICT` and report through :func:`one_line`, so a wrong type,
an out-of-range number, NaN/inf, a missing or an unknown key all read the same way::

    configs/x.toml: `steps` must be an integer, got 'many'

Like ``sim.atomic`` this lives in the lowest package so that ``robot`` (deploy, no torch) and
``hydo_cli`` share it; it imports pydantic only.
"""

from __future__ import annotations

from typing import Any

from pydantic import ConfigDict, ValidationError

#: Strict: ``"5"`` is not 5 and ``true`` is not 1 (a TOML/JSON user meant something else); unknown keys
#: are refused (a typo must not silently fall back to the default); NaN and inf are never a setting.
STRICT = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)

#: pydantic error type -> what was expected, in words (the context fills the numbers).
_EXPECTED = {
    "int_type": "an integer",
    "int_from_float": "an integer",
    "float_type": "a number",
    "string_type": "a string",
    "bool_type": "true or false",
    "dict_type": "a mapping",
    "list_type": "a list",
    "tuple_type": "a list",
    "finite_number": "a finite number (no NaN or inf)",
    "greater_than_equal": "a number >= {ge}",
    "greater_than": "a number > {gt}",
    "less_than_equal": "a number <= {le}",
    "less_than": "a number < {lt}",
    "string_too_short": "a non-empty string",
    "string_pattern_mismatch": "a string matching {pattern}",
    "too_short": "at least {min_length} items",
    "too_long": "at most {max_length} items",
    "literal_error": "one of {expected}",
    "enum": "one of {expected}",
    "none_required": "null",
}


def _found(value: Any) -> str:
    """The offending value, short and on one line."""
    text = repr(value).replace("\n", " ")
    return text if len(text) <= 80 else text[:77] + "..."


def key_of(loc: tuple) -> str:
    """pydantic's error location as the dotted key a user writes (``agent.gamma``, ``cameras[1].fps``)."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def one_line(err: ValidationError, source: str, prefix: str = "") -> str:
    """The first problem of ``err`` as ``SOURCE: `KEY` must be EXPECTED, got FOUND`` (one line; how many
    more problems there are is appended, so fixing one never hides that others wait). ``prefix``: the
    key of the value the schema checked (``agent``, ``cameras[0].T_base_camera``)."""
    errors = err.errors(include_url=False)
    e = errors[0]
    # Union members report their own locations (``int``, ``none``): the user's key is what came before.
    loc = tuple(p for p in e["loc"] if p not in ("int", "float", "str", "none", "bool", "dict", "list"))
    loc = tuple(p for p in loc if not (isinstance(p, str) and p.startswith(("function-", "constrained-"))))
    inner = key_of(loc)
    if prefix and inner:
        key = prefix + ("" if inner.startswith("[") else ".") + inner
    else:
        key = prefix or inner
    kind = e["type"]
    if kind == "missing":
        text = f"`{key}` is missing"
    elif kind in ("extra_forbidden", "unexpected_keyword_argument"):
        text = f"`{key}` is not a known key"
    elif kind == "value_error":  # a cross-check of the schema: its message is the whole story
        msg = str(e.get("ctx", {}).get("error", e["msg"])).removeprefix("Value error, ")
        text = f"`{key}` {msg}" if key else msg
    else:
        want = _EXPECTED.get(kind)
        want = want.format(**e.get("ctx", {})) if want else e["msg"].lower().removeprefix("input should be ")
        text = f"`{key}` must be {want}, got {_found(e.get('input'))}"
    if len(errors) > 1:
        text += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return f"{source}: {text}"

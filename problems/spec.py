"""Specification strings, ``name:key=value,...``, shared by the problem and integrator
registries: splitting, typed values, and the error and hint they raise and give."""

from __future__ import annotations

import difflib


class SpecError(ValueError):
    """A problem or integrator specification that cannot be understood."""


def suggest(name: str, valid) -> str:
    """A ' (did you mean ...?)' hint, or an empty string."""
    close = difflib.get_close_matches(name, list(valid), n=3, cutoff=0.5)
    return f" (did you mean {', '.join(close)}?)" if close else ""


def parse_value(text: str, default, where: str):
    """Convert ``text`` to the type of ``default``."""
    try:
        if isinstance(default, bool):
            low = text.strip().lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return low in ("true", "1", "yes")
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
        return text
    except ValueError:
        raise SpecError(f"{where}: {text!r} is not a valid {type(default).__name__}") from None


def split_spec(spec: str) -> tuple[str, dict[str, str]]:
    """Split ``name:key=value,key=value`` into the name and raw option strings."""
    name, _, rest = spec.partition(":")
    name = name.strip()
    options: dict[str, str] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, value = item.partition("=")
            if not eq or not key.strip():
                raise SpecError(f"{spec!r}: option {item!r} is not of the form key=value")
            if key.strip() in options:  # the last value winning would hide a typo
                raise SpecError(f"{spec!r}: {key.strip()!r} is given twice")
            options[key.strip()] = value.strip()
    return name, options

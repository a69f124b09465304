"""Label values: states in [0, 1], or physical units with the range that maps to them (`--degrees 0:90`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..errors import InputError

_TOL = 1e-9  # a state this far outside [0, 1] is rounding, not a mistake


# ----------------------------------------------------------------------------------------------------------------
# Units
# ----------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Unit:
    """A physical unit with the range that maps to states 0 .. 1 (lo may exceed hi: '90:0' = closed at 90)."""

    name: str  # "degrees" or "cm"
    lo: float
    hi: float

    def normalise(self, value: float) -> float:
        return (value - self.lo) / (self.hi - self.lo)

    def __str__(self) -> str:
        return f"{self.name} {self.lo:g}:{self.hi:g}"


UNIT_ALIASES = {
    "": None, "norm": None, "normalised": None, "normalized": None, "state": None, "0-1": None,
    "deg": "degrees", "degree": "degrees", "degrees": "degrees", "°": "degrees",
    "rad": "radians", "radian": "radians", "radians": "radians",
    "cm": "cm", "mm": "mm", "m": "m",
}
_TO_BASE = {"radians": ("degrees", 180.0 / math.pi), "mm": ("cm", 0.1), "m": ("cm", 100.0)}


def parse_range(text: str | tuple[float, float] | None, unit: str) -> Unit | None:
    """'0:90' (or a (lo, hi) pair) -> Unit; InputError naming the option when it does not parse."""
    if text is None:
        return None
    if isinstance(text, (tuple, list)):
        parts = [str(t) for t in text]
    else:
        parts = str(text).split(":")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"--{unit} {text!r}: expected LO:HI, e.g. --{unit} 0:90") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
        raise InputError(f"--{unit} {text!r}: LO and HI must be finite and different")
    return Unit(unit, lo, hi)


def normalise_value(value: Any, unit: Unit | None = None, where: str = "value", row_unit: str | None = None,
                    units: dict[str, Unit] | None = None) -> float:
    """A state in [0, 1] from a raw value, optionally in a physical unit; InputError on NaN / out of range."""
    try:
        v = float(str(value).strip()) if not isinstance(value, (int, float)) else float(value)
    except ValueError:
        raise InputError(f"{where}: {value!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {value!r} is not a finite number (NaN / inf cannot be a state)")
    if row_unit is not None:
        key = row_unit.strip().lower()
        if key not in UNIT_ALIASES:
            raise InputError(f"{where}: unknown unit {row_unit!r}; use one of deg, rad, cm, mm, m or leave it empty")
        base = UNIT_ALIASES[key]
        if base in _TO_BASE:
            base, factor = _TO_BASE[base]
            v *= factor
        if base is None:
            unit = None
        else:
            unit = (units or {}).get(base)
            if unit is None:
                raise InputError(f"{where}: the value is in {base}; give its range, e.g. --{base} 0:90")
    raw = v
    if unit is not None:
        v = unit.normalise(v)
    if -_TOL <= v <= 1 + _TOL:
        return min(max(v, 0.0), 1.0)
    shown = f"{raw:g} {unit.name} is outside the range {unit.lo:g}:{unit.hi:g}" if unit else f"{raw:g} is outside [0, 1]"
    hint = "" if unit else " (give physical values with --degrees LO:HI or --cm LO:HI)"
    raise InputError(f"{where}: {shown}{hint}")

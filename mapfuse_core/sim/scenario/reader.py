"""Typed, validating access to a parsed scenario TOML document (dotted-key errors,
angles as multiples of π)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

from mapfuse_core.sensor import MAX_ANGLE_SIGMA
from mapfuse_core.sim.limits import MAX_FEATURE_ID, MAX_MAGNITUDE
from mapfuse_core.sim.scenario.types import ScenarioError


class _Reader:
    """Typed access to a parsed TOML document, raising ScenarioError with dotted keys."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, reason: str) -> ScenarioError:
        return ScenarioError(self.source, key, reason)

    def table(
        self,
        value: object,
        key: str,
        required: Sequence[str] = (),
        optional: Sequence[str] = (),
    ) -> dict[str, Any]:
        """A table with exactly the allowed keys and at least the required ones."""
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a table, got {_tname(value)}")
        allowed = set(required) | set(optional)
        for k in value:
            if k not in allowed:
                hint = f"; allowed: {', '.join(sorted(allowed))}" if allowed else ""
                raise self.fail(_join(key, k), f"unknown key{hint}")
        for k in required:
            if k not in value:
                raise self.fail(_join(key, k), "missing required key")
        return value

    def number(
        self,
        value: object,
        key: str,
        *,
        positive: bool = False,
        nonneg: bool = False,
        angle: bool = False,
    ) -> float:
        """A finite float of magnitude at most :data:`MAX_MAGNITUDE` (ints accepted);
        angles may be ``"k*pi/n"`` strings."""
        if angle and isinstance(value, str):
            x = _parse_pi(value)
            if x is None:
                raise self.fail(
                    key, f"cannot read angle {value!r}: write a number or e.g. 'pi/3', '-2*pi/5'"
                )
        elif isinstance(value, bool) or not isinstance(value, int | float):
            what = "a number or a 'k*pi/n' string" if angle else "a number"
            raise self.fail(key, f"must be {what}, got {_tname(value)}")
        else:
            x = float(value)
        if not math.isfinite(x):
            raise self.fail(key, f"must be finite, got {x}")
        if abs(x) > MAX_MAGNITUDE:
            raise self.fail(key, f"must be within ±1e9 (the documented maximum), got {x:g}")
        if positive and x <= 0.0:
            raise self.fail(key, f"must be > 0, got {x}")
        if nonneg and x < 0.0:
            raise self.fail(key, f"must be >= 0, got {x}")
        return x

    def integer(
        self,
        value: object,
        key: str,
        *,
        minimum: int | None = None,
        maximum: int | None = None,
        what: str = "",
    ) -> int:
        """An integer in ``minimum … maximum`` (``what`` names the maximum in the error)."""
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"must be an integer, got {_tname(value)}")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            limit = what or f"{maximum:,}"
            raise self.fail(key, f"must be <= {limit} (the documented maximum), got {value}")
        return value

    def string(self, value: object, key: str) -> str:
        if not isinstance(value, str):
            raise self.fail(key, f"must be a string, got {_tname(value)}")
        return value

    def array(self, value: object, key: str) -> list[Any]:
        if not isinstance(value, list):
            raise self.fail(key, f"must be an array, got {_tname(value)}")
        return value

    def vector(self, value: object, key: str, n: int, angle_last: bool = False) -> list[float]:
        items = self.array(value, key)
        if len(items) != n:
            raise self.fail(key, f"must have {n} entries, got {len(items)}")
        return [
            self.number(v, f"{key}[{i}]", angle=angle_last and i == n - 1)
            for i, v in enumerate(items)
        ]

    def feature_id(self, value: object, key: str) -> int:
        """A feature id, ``0 … 2**63 - 1`` (int64 in the log)."""
        return self.integer(value, key, minimum=0, maximum=MAX_FEATURE_ID, what="2**63 - 1")

    def sigma(self, value: object, key: str, *, angle: bool = False) -> float:
        """A standard deviation: > 0 with a square that is a finite, non-zero float; at
        most π for an angle."""
        x = self.number(value, key, positive=True, angle=angle)
        if angle and x > MAX_ANGLE_SIGMA:
            raise self.fail(key, f"an angle's standard deviation must be <= pi, got {x:g}")
        if not 1e-300 <= x * x < math.inf:
            raise self.fail(key, f"{x:g} squared is not a usable variance (give at least 1e-150)")
        return x


_PI_RE = re.compile(
    r"^\s*(?P<sign>[+-]?)\s*(?:(?P<k>\d+(?:\.\d*)?|\.\d+)\s*\*\s*)?pi"
    r"\s*(?:/\s*(?P<n>\d+(?:\.\d*)?|\.\d+))?\s*$"
)


def _parse_pi(text: str) -> float | None:
    """``[±][k*]pi[/n]`` → float, else ``None``."""
    m = _PI_RE.match(text)
    if m is None:
        return None
    k = float(m["k"]) if m["k"] else 1.0
    n = float(m["n"]) if m["n"] else 1.0
    if n == 0.0:
        return None
    x = k * math.pi / n
    return -x if m["sign"] == "-" else x


def _tname(value: object) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return f"{type(value).__name__} {value!r}"


def _join(key: str, sub: str) -> str:
    return f"{key}.{sub}" if key else sub

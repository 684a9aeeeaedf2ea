"""Argument checks shared by the environments: each raises ``ValueError("<name> must be <rule>, got <value>")``.

The constructors check every kwarg up front, so a bad transfer-target setting fails at
``gymnasium.make`` with the name of the offending argument; ``reset`` and ``step`` check their
inputs with :func:`state_option` and :func:`action_vector`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping
from numbers import Integral, Real
from typing import Any

import numpy as np


def require(ok: bool, name: str, value: object, rule: str) -> None:
    """Raise ``ValueError("<name> must be <rule>, got <value!r>")`` unless `ok`."""
    if not ok:
        raise ValueError(f"{name} must be {rule}, got {value!r}")


def is_real(value: object) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def positive(name: str, value: object) -> float:
    """`value` as a float if it is a finite number > 0."""
    require(is_real(value) and value > 0, name, value, "a finite number > 0")  # type: ignore[operator]
    return float(value)  # type: ignore[arg-type]


def nonzero(name: str, value: object) -> float:
    """`value` as a float if it is a finite number other than 0."""
    require(is_real(value) and value != 0, name, value, "a finite number other than 0")  # type: ignore[operator]
    return float(value)  # type: ignore[arg-type]


def nonnegative(name: str, value: object) -> float:
    """`value` as a float if it is a finite number >= 0."""
    require(is_real(value) and value >= 0, name, value, "a finite number >= 0")  # type: ignore[operator]
    return float(value)  # type: ignore[arg-type]


def positive_integer(name: str, value: object) -> int:
    """`value` as an int if it is an integer >= 1 (not a bool): a horizon or a repeat count."""
    require(
        isinstance(value, Integral) and not isinstance(value, bool) and value >= 1,
        name,
        value,
        "an integer >= 1",
    )
    return int(value)  # type: ignore[call-overload]


def finite_array(
    name: str,
    value: object,
    dim: int,
    rule: str,
    *,
    minimum: float | None = None,
    strict: bool = False,
    scalar_ok: bool = False,
) -> np.ndarray:
    """`value` as a fresh float array of shape `(dim,)` if it is `dim` finite numbers.

    With `minimum`, every entry must also be >= `minimum` (> with `strict`); with `scalar_ok`, a
    single number is accepted and repeated `dim` times. `rule` is the error message's wording.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = np.full(0, np.nan)
    shapes = ((dim,), ()) if scalar_ok else ((dim,),)
    ok = arr.shape in shapes and bool(np.all(np.isfinite(arr)))
    if ok and minimum is not None:
        ok = bool(np.all(arr > minimum) if strict else np.all(arr >= minimum))
    require(ok, name, value, rule)
    return np.broadcast_to(arr, (dim,)).copy()


def finite_tuple(name: str, value: object, dim: int, *, positive: bool) -> tuple[float, ...]:
    """`dim` finite numbers, each > 0 (`positive`) or >= 0, as a tuple of floats."""
    rule = f"{dim} finite numbers {'> 0' if positive else '>= 0'}"
    return tuple(finite_array(name, value, dim, rule, minimum=0.0, strict=positive).tolist())


def check_render_mode(value: str | None, modes: Collection[str]) -> str | None:
    """`value` if it is None or one of `modes` (the env's ``metadata["render_modes"]``)."""
    require(value is None or value in modes, "render_mode", value, f"None or one of {modes}")
    return value


def state_option(
    options: Mapping[str, Any] | None,
    dim: int,
    *,
    condition: Callable[[np.ndarray], bool] | None = None,
    rule: str = "",
) -> np.ndarray | None:
    """``options["state"]`` of ``reset`` as a fresh float array of `dim` finite numbers; None if absent.

    `condition` is an extra requirement on the state, worded by `rule` (e.g. ``"z >= 0"``).
    """
    if options is None or options.get("state") is None:
        return None
    state = np.asarray(options["state"], dtype=float)
    ok = state.shape == (dim,) and bool(np.all(np.isfinite(state)))
    if not (ok and (condition is None or condition(state))):
        extra = f", {rule}" if rule else ""
        raise ValueError(f"options['state'] must be {dim} finite numbers{extra}, got {state}")
    return state.copy()


def action_vector(action: object, dim: int) -> np.ndarray:
    """The action of ``step`` as a flat float array of `dim` finite numbers (not yet clipped)."""
    a = np.asarray(action, dtype=float).reshape(-1)
    if a.shape != (dim,) or not np.all(np.isfinite(a)):
        noun = "number" if dim == 1 else "numbers"
        raise ValueError(f"action must be {dim} finite {noun}, got {action!r}")
    return a

"""Numerical-derivative helpers and hypothesis strategies shared by the Jacobian tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from hypothesis import strategies as st

from mapfuse_core.geometry.se2 import wrap_angle

# Central differences with h = 1e-6 have truncation error O(h²·f''') ≈ 1e-12 and
# round-off O(ε·|f|/h) ≈ 1e-10·|f| for |f| ≲ 100 m, so 1e-6 absolute plus 1e-6
# relative is a tolerance a wrong entry (error ≥ 1e-3 for our inputs) cannot pass.
STEP = 1e-6
ATOL = 1e-6
RTOL = 1e-6


def numerical_jacobian(
    f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, angle_rows: tuple[int, ...] = ()
) -> np.ndarray:
    """Central-difference Jacobian of ``f`` at ``x``.

    Rows listed in ``angle_rows`` are differenced through a wrap so that a value
    that jumps across ±π (or ±π/2 for line angles) is still differentiated right.
    """
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x), dtype=float)
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = STEP
        d = np.asarray(f(x + dx), dtype=float) - np.asarray(f(x - dx), dtype=float)
        for r in angle_rows:
            # wrap to (−π/2, π/2] first covers both 2π and π jumps of line angles
            d[r] = float(wrap_angle(d[r]))
            if abs(d[r]) > math.pi / 2:
                d[r] -= math.copysign(math.pi, d[r])
        J[:, i] = d / (2 * STEP)
    return J


coord = st.floats(min_value=-100.0, max_value=100.0, allow_nan=False, allow_infinity=False)
near_pi = st.floats(min_value=math.pi - 1e-3, max_value=math.pi, allow_nan=False)
angle = st.one_of(
    st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False),
    near_pi,
    near_pi.map(lambda a: -a),
    st.floats(min_value=-1e-4, max_value=1e-4, allow_nan=False),
)


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:
    """Poses ``(x, y, θ)`` with θ often within 1e-3 of ±π and of 0."""
    return np.array([draw(coord), draw(coord), float(wrap_angle(draw(angle)))])


@st.composite
def circles(draw: st.DrawFn) -> np.ndarray:
    """Circles ``(x, y, r)`` with radius in [0.05, 3] m."""
    r = draw(st.floats(min_value=0.05, max_value=3.0, allow_nan=False))
    return np.array([draw(coord), draw(coord), r])

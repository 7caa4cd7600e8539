"""Documented maxima of a simulation, checked before anything is allocated
(``docs/conventions.md`` lists them with their messages).

The bounds come from memory use: a simulated run keeps per-step arrays (true pose,
controls, odometry and its 3×3 covariance: 17 floats, 136 bytes a step) and every
raw scan (bearing, range and hit id per beam: 24 bytes a beam), and the ray caster
works on beams × features arrays per scan.
"""

from __future__ import annotations

from numbers import Integral

from mapfuse_core.sensor.laser import MAX_ANGLE_SIGMA, MAX_BEAMS

__all__ = [
    "MAX_ANGLE_SIGMA",
    "MAX_BEAMS",
    "MAX_FEATURE_ID",
    "MAX_MAGNITUDE",
    "MAX_SCAN_BEAMS",
    "MAX_SEED",
    "MAX_STEPS",
    "check_seed",
    "check_steps",
]

MAX_MAGNITUDE = 1e9
"""Largest magnitude of any number in a scenario file: coordinates to 1e9 m (float64
still resolves 1e-7 m there, and UTM-like surveyed coordinates are below 1e7 m),
speeds, ranges and standard deviations likewise, so that squares and products of
them stay finite."""


MAX_SEED = 2**63 - 1
"""Largest seed: seeds are stored as int64 in the measurement log (``0 ≤ seed ≤ 2⁶³ − 1``)."""

MAX_FEATURE_ID = 2**63 - 1
"""Largest feature id: ids are int64 arrays in the log (``0 ≤ id ≤ 2⁶³ − 1``)."""

MAX_STEPS = 1_000_000
"""Most poses a simulation drives: the per-step arrays then take 136 MB."""


MAX_SCAN_BEAMS = 100_000_000
"""Most beams of a whole simulation, steps × beams per scan: the kept raw scans then
take 2.4 GB."""


def check_seed(seed: object, what: str = "seed") -> int:
    """``seed`` as an int in ``0 … MAX_SEED``, else :class:`ValueError` naming ``what``."""
    if isinstance(seed, bool) or not isinstance(seed, Integral):
        raise ValueError(f"{what} must be an integer, got {seed!r}")
    value = int(seed)
    if not 0 <= value <= MAX_SEED:
        raise ValueError(f"{what} must be in 0 … 2**63 - 1, got {value}")
    return value


def check_steps(steps: int, beams: int, what: str = "steps") -> None:
    """:class:`ValueError` naming ``what`` when ``steps`` poses of ``beams`` beams exceed
    :data:`MAX_STEPS` or :data:`MAX_SCAN_BEAMS`."""
    if steps > MAX_STEPS:
        raise ValueError(f"{what} = {steps} is above the maximum of {MAX_STEPS:,} steps")
    if steps * beams > MAX_SCAN_BEAMS:
        raise ValueError(
            f"{what} = {steps} with {beams} beams a scan is {steps * beams:,} beams, above "
            f"the maximum of {MAX_SCAN_BEAMS:,} (steps × laser.n_beams)"
        )

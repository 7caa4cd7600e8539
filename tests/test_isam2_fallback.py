"""iSAM2 and the fixed-lag smoother solve again with QR when Cholesky finds the system
indeterminate (GTSAM's exception, raised to Python as a ``RuntimeError``).

The anchor's loose prior (σ 100 m) next to its ties (σ 1 mm) can make a Cholesky pivot
vanish in round-off, as on CARMEN's Belgioioso log; QR solves it.  The exception is
injected here on the first, Cholesky run, so the test holds whatever the data.
"""

from __future__ import annotations

import numpy as np
import pytest

import mapfuse_graph.solvers as solvers
from mapfuse_graph.solvers import FixedLagOptions, ISAM2Options, run_graph
from tests.synthetic import synthetic_log

_INDETERMINATE = (
    "\nIndeterminate linear system detected while working near variable\n"
    "6989586621679009792 (Symbol: a0)."
)


@pytest.mark.parametrize("backend", ["isam2", "fixedlag"])
def test_indeterminate_cholesky_is_solved_again_with_qr(
    monkeypatch: pytest.MonkeyPatch, backend: str
) -> None:
    log = synthetic_log(steps=60, seed=2)
    kw = {"fixedlag": FixedLagOptions(lag_s=5.0)} if backend == "fixedlag" else {}
    want = run_graph(
        log, backend, fusion=True, association="truth", isam2=ISAM2Options(factorization="QR"), **kw
    )
    used: list[str] = []
    real_isam2, real_fixedlag = solvers._run_isam2, solvers._run_fixedlag

    def isam2(builder, options, *a):  # type: ignore[no-untyped-def]
        used.append(options.factorization if options else "CHOLESKY")
        if used[-1] == "CHOLESKY":
            raise RuntimeError(_INDETERMINATE)
        return real_isam2(builder, options, *a)

    def fixedlag(builder, fl, options, *a):  # type: ignore[no-untyped-def]
        used.append(options.factorization if options else "CHOLESKY")
        if used[-1] == "CHOLESKY":
            raise RuntimeError(_INDETERMINATE)
        return real_fixedlag(builder, fl, options, *a)

    monkeypatch.setattr(solvers, "_run_isam2", isam2)
    monkeypatch.setattr(solvers, "_run_fixedlag", fixedlag)
    with pytest.warns(RuntimeWarning, match="solved again with QR factorization"):
        got = run_graph(log, backend, fusion=True, association="truth", **kw)
    assert used == ["CHOLESKY", "QR"]
    assert got.details.extra["factorization"].startswith("QR")
    # A fresh builder: the same answer as a QR run from the start.
    np.testing.assert_array_equal(got.smoothed.poses, want.smoothed.poses)


def test_other_errors_and_qr_failures_are_not_retried(monkeypatch: pytest.MonkeyPatch) -> None:
    log = synthetic_log(steps=30, seed=2)
    calls: list[str] = []

    def failing(builder, options, *a):  # type: ignore[no-untyped-def]
        calls.append(options.factorization if options else "CHOLESKY")
        raise RuntimeError(_INDETERMINATE)

    monkeypatch.setattr(solvers, "_run_isam2", failing)
    with pytest.raises(RuntimeError, match="Indeterminate"):
        run_graph(log, "isam2", association="truth", isam2=ISAM2Options(factorization="QR"))
    assert calls == ["QR"]

    def other(builder, options, *a):  # type: ignore[no-untyped-def]
        raise RuntimeError("something else")

    monkeypatch.setattr(solvers, "_run_isam2", other)
    with pytest.raises(RuntimeError, match="something else"):
        run_graph(log, "isam2", association="truth")

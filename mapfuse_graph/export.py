"""Export a solved graph: the pose graph as g2o, everything g2o cannot hold in a JSON sidecar.

The g2o format holds ``VERTEX_SE2`` poses and ``EDGE_SE2`` relative-pose edges with
their information matrices (upper triangle, row by row), which is exactly the
odometry chain of a mapfuse graph.  It has no standard type for the line landmarks
``(ρ, α)``, the circle observations with their radius, the tie factors through the
anchor, or the priors, which are Python ``CustomFactor`` objects; GTSAM's own
``writeG2o`` drops them without a word.  :func:`export_graph` writes:

* ``graph.g2o`` — one ``VERTEX_SE2 k x y θ`` per step ``k`` (its final estimate) and
  one ``EDGE_SE2`` per odometry factor; no comment lines, since GTSAM's ``readG2o``
  stops reading edges at one;
* ``graph.json`` — what the g2o file leaves out, by name and count, with the value and
  meaning (:mod:`mapfuse_graph.keys`) of every variable it does not hold, and the
  mapping of g2o vertex ids to graph keys.

So no partial file is silent: the sidecar, and the returned :class:`GraphExport`,
name every factor and variable not in the g2o file.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.estimate import EstimatorResult
from mapfuse_graph.keys import describe_key, symbol_name
from mapfuse_graph.results import GraphDetails

__all__ = ["GraphExport", "export_graph"]

# What a factor is, by its class and the symbol characters of its keys.
_FACTOR_NAMES: dict[tuple[str, str], str] = {
    ("PriorFactorPose2", "x"): "prior on the first pose (fixes Wglobal)",
    ("PriorFactorPose2", "a"): "loose prior on the anchor",
    ("PriorFactorVector", "k"): "prior on a known line",
    ("PriorFactorVector", "q"): "prior on a known circle",
    ("PriorFactorVector", "r"): "radius observation (split circles)",
    ("CustomFactor", "k"): "prior on a known line",
    ("CustomFactor", "xl"): "line observation",
    ("CustomFactor", "xc"): "circle observation",
    ("CustomFactor", "alk"): "line tie (landmark = known line through the anchor)",
    ("CustomFactor", "acq"): "circle tie (landmark = known circle through the anchor)",
}


@dataclass(frozen=True)
class GraphExport:
    """What :func:`export_graph` wrote and what it left out."""

    g2o: Path
    """The g2o file (poses and odometry edges)."""
    sidecar: Path
    """The JSON sidecar (everything else, by name)."""
    vertices: int
    """``VERTEX_SE2`` lines written (one per step)."""
    edges: int
    """``EDGE_SE2`` lines written (one per odometry factor)."""
    left_out_factors: dict[str, int]
    """Factors not in the g2o file: what they are → how many."""
    left_out_variables: int
    """Variables not in the g2o file (landmarks, known features, the anchor)."""

    def summary(self) -> str:
        """One line naming what the g2o file holds and what it leaves out."""
        out = ", ".join(f"{n} {name}" for name, n in self.left_out_factors.items())
        return (
            f"{self.g2o.name}: {self.vertices} poses and {self.edges} odometry edges; "
            f"left out (in {self.sidecar.name}): {self.left_out_variables} variables"
            + (f" and factors: {out}" if out else "")
        )


def _chars(factor: Any) -> str:
    held = factor.keys()  # bound first: the key container must outlive the iteration
    return "".join(chr(gtsam.Symbol(int(k)).chr()) for k in held)


def _value(values: gtsam.Values, key: int) -> list[float]:
    if symbol_name(key)[0] in "xa":
        p = values.atPose2(key)
        return [float(p.x()), float(p.y()), float(p.theta())]
    return [float(v) for v in np.asarray(values.atVector(key), dtype=float).ravel()]


def _upper(info: np.ndarray) -> list[float]:
    return [float(info[i, j]) for i in range(3) for j in range(i, 3)]


def export_graph(result: EstimatorResult, folder: str | Path, name: str = "graph") -> GraphExport:
    """Write ``folder/name.g2o`` and ``folder/name.json`` for the graph of ``result``, a
    graph backend's run (:func:`~mapfuse_graph.solvers.run_graph`)."""
    details = result.details
    if not isinstance(details, GraphDetails):
        raise ValueError(f"the {result.estimator} result holds no factor graph to export")
    graph, values = details.graph, details.values
    if graph is None or values is None:
        raise ValueError("this graph result holds no graph (made without run_graph)")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    n = int(result.poses.shape[0])
    pose_keys = {int(gtsam.symbol("x", k)): k for k in range(n)}
    lines: list[str] = []
    for k in range(n):
        x, y, th = _value(values, int(gtsam.symbol("x", k)))
        lines.append(f"VERTEX_SE2 {k} {x:.12g} {y:.12g} {th:.12g}")
    edges = 0
    left: Counter[str] = Counter()
    for i in range(graph.size()):
        f = graph.at(i)
        if f is None:
            continue
        kind = type(f).__name__
        held = f.keys()
        keys = [int(k) for k in held]
        if isinstance(f, gtsam.BetweenFactorPose2) and all(k in pose_keys for k in keys):
            m = f.measured()
            noise: Any = f.noiseModel()  # a Gaussian model (stubs type it as Base)
            info = np.array(noise.information(), dtype=np.float64)
            a, b = (pose_keys[k] for k in keys)
            nums = [m.x(), m.y(), m.theta(), *_upper(info)]
            lines.append(f"EDGE_SE2 {a} {b} " + " ".join(f"{v:.12g}" for v in nums))
            edges += 1
            continue
        chars = "".join(sorted(set(_chars(f)), key=_chars(f).index))
        left[_FACTOR_NAMES.get((kind, chars), f"{kind} on {'-'.join(chars)}")] += 1
    g2o_path = out / f"{name}.g2o"
    g2o_path.write_text("\n".join(lines) + "\n")
    held_values = values.keys()
    others = [int(k) for k in held_values if int(k) not in pose_keys]
    variables = {
        symbol_name(k): {"is": describe_key(k), "value": _value(values, k)} for k in others
    }
    sidecar = {
        "g2o": g2o_path.name,
        "g2o_holds": {
            "VERTEX_SE2": f"{n} poses: vertex id k is the graph key x<k>, "
            "the vehicle pose x^Wglobal_R of step k at its final estimate",
            "EDGE_SE2": f"{edges} odometry factors (BetweenFactorPose2), measurement and "
            "information upper triangle",
        },
        "left_out": {
            "factors": dict(left),
            "variables": variables,
            "why": "g2o has no standard type for these: line landmarks (ρ, α), circle "
            "observations with their radius, tie factors through the anchor, priors. "
            "The full graph is GraphDetails.graph (GTSAM objects).",
        },
        "backend": result.estimator,
        "fusion": result.fusion,
        "association": result.association,
        "scenario": result.scenario,
        "seed": result.seed,
    }
    side_path = out / f"{name}.json"
    side_path.write_text(json.dumps(sidecar, indent=2, ensure_ascii=False) + "\n")
    return GraphExport(
        g2o=g2o_path,
        sidecar=side_path,
        vertices=n,
        edges=edges,
        left_out_factors=dict(left),
        left_out_variables=len(variables),
    )

"""``changes.png``: the known map coloured by change class (:func:`changes_figure`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from mapfuse.plotting import draw_circle, draw_line_feature
from mapfuse_core.changes import ChangeReport, ChangeStatus
from mapfuse_core.evaluation.change_truth import ChangeTruth
from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.geometry.se2 import FloatArray, compose
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import Scenario

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["CLASS_COLOURS", "changes_figure"]

#: Colour of each class in the figure.
CLASS_COLOURS = {
    ChangeStatus.CONFIRMED: "tab:green",
    ChangeStatus.MOVED: "tab:orange",
    ChangeStatus.MISSING: "tab:red",
    ChangeStatus.UNOBSERVED: "0.7",
    ChangeStatus.INCONCLUSIVE: "tab:purple",
}


def _draw(ax: Axes, kind: int, p: FloatArray, extent: FloatArray | None, **kw: object) -> None:
    """A feature in its class's style; a circle also gets a centre marker of fixed size
    on screen (small beacons stay visible at any map extent), which carries the label
    so that the legend shows the marker, not a patch's rectangle."""
    if kind == int(FeatureKind.CIRCLE):
        label = kw.pop("label", None)
        draw_circle(ax, p, **kw)
        ax.plot(
            [p[0]],
            [p[1]],
            ls="none",
            marker="o",
            ms=7,
            mfc="none",
            mew=1.5,
            mec=kw.get("color", "k"),
            label=label,
        )
        return
    e = (-5.0, 5.0) if extent is None or not np.all(np.isfinite(extent)) else tuple(extent)
    draw_line_feature(ax, p, (float(e[0]), float(e[1])), **kw)


def changes_figure(
    report: ChangeReport,
    log: MeasurementLog,
    poses: FloatArray,
    scenario: Scenario | None = None,
    truth: ChangeTruth | None = None,
) -> Figure:
    """Known map by class, arrows for the moves, new features in blue, the estimated
    trajectory; in simulation (``scenario`` and ``truth``) the true changes beside
    them: true places of moved features dotted, removed ones crossed, added ones in
    purple.  Everything in ``Wknown``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 9))
    known = log.known_map
    ext = known.extents
    labelled: set[str] = set()
    for r, c in enumerate(report.known):
        col = CLASS_COLOURS[c.status]
        label = c.status.value if c.status.value not in labelled else None
        labelled.add(c.status.value)
        p = known.params[r]
        _draw(
            ax,
            int(known.kinds[r]),
            p,
            None if ext is None else ext[r],
            color=col,
            lw=2.0,
            label=label,
        )
        if c.status == ChangeStatus.MOVED and np.all(np.isfinite(c.displacement[:2])):
            ax.annotate(
                "",
                xy=(p[0] + c.displacement[0], p[1] + c.displacement[1]),
                xytext=(p[0], p[1]),
                arrowprops={"arrowstyle": "->", "color": col, "lw": 1.5},
            )
    for i, n in enumerate(report.new):
        _draw(
            ax,
            int(n.kind),
            n.params,
            None,
            color="tab:blue",
            lw=1.5,
            label="new" if i == 0 else None,
        )
    P = np.array([compose(report.x_Wknown_Wglobal, x) for x in poses if np.all(np.isfinite(x))])
    if P.size:
        ax.plot(P[:, 0], P[:, 1], color="k", lw=0.8, label="estimated trajectory")
    if scenario is not None and truth is not None:
        _draw_truth(ax, scenario, truth, log)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, Wknown)")
    ax.set_ylabel("y (m, Wknown)")
    counts = report.counts()
    verdict = "" if report.conclusive else "INCONCLUSIVE (run not consistent), "
    ax.set_title(
        "Known-map changes: "
        + verdict
        + ", ".join(f"{k} {v}" for k, v in counts.items() if k != "duplicates")
        + f" (χ² level {report.level})"
    )
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def _draw_truth(ax: Axes, scenario: Scenario, truth: ChangeTruth, log: MeasurementLog) -> None:
    frame = scenario.known_map.frame
    first = {"removed": True}
    lengths = {s.id: (-0.5 * s.length, 0.5 * s.length) for s in scenario.world.segments}

    def draw_world_features(fids: Iterable[int], label: str, **style: object) -> None:
        """The true features ``fids`` in ``Wknown``, labelled once."""
        for n, fid in enumerate(f for f in fids if f in scenario.world.ids):
            kind, p = scenario.world.feature(fid)
            q = express_in(kind, frame, p)[0]
            ext = np.array(lengths.get(fid, (-5.0, 5.0)))
            _draw(ax, int(kind), q, ext, lw=1.0, label=label if n == 0 else None, **style)

    draw_world_features(truth.moved, "true place of moved", color="k", ls=":")
    ids = log.known_map.ids.tolist()
    for fid in truth.removed:
        r = ids.index(fid)
        p = log.known_map.params[r]
        ax.plot(
            p[0],
            p[1],
            "x",
            color="tab:red",
            ms=10,
            label="truly removed" if first["removed"] else None,
        )
        first["removed"] = False
    draw_world_features(truth.added, "truly added", color="tab:purple", ls="--")

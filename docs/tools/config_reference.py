"""Writes ``docs/configuration.md``: every field of the options dataclasses, its meaning,
its default and a link to the measurements behind it.

The fields, their defaults and their meanings come from the dataclasses themselves (the
meaning is the first sentence of each field's docstring), so the page cannot drift from
the code: ``tests/test_docs_pages.py`` fails when the committed page differs from what
this script writes.  The evidence links are the one hand-kept part (:data:`EVIDENCE`).

    PYTHONPATH=. python docs/tools/config_reference.py          # rewrite the page
    PYTHONPATH=. python docs/tools/config_reference.py --check  # exit 1 when stale
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import itertools
import math
import re
import sys
import textwrap
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "configuration.md"


@dataclasses.dataclass(frozen=True)
class Section:
    """One dataclass on the page."""

    target: str
    """``module:ClassName``."""
    where: str
    """Where the dataclass is used, one sentence of Markdown."""


SECTIONS: tuple[tuple[str, tuple[Section, ...]], ...] = (
    (
        "The EKF reference",
        (
            Section(
                "ekf_reference.config:EKFConfig",
                "The `ekf` estimator's options (`run_ekf(log, config)`); `EKFConfig.paper()` is "
                "the paper's method ([Method §8](method.md#8-the-papers-method-and-the-default-"
                "configuration)).",
            ),
            Section(
                "ekf_reference.known_gating:KnownGatingParams",
                "`EKFConfig.known_gating`: the known-map gate "
                "([change detection](change-detection.md#the-known-map-gate)).",
            ),
            Section(
                "ekf_reference.anchor_watch:AnchorWatchParams",
                "`EKFConfig.anchor_watch`: the checks that undo an anchor its known features "
                "contradict ([Method §5.2](method.md#52-the-anchor)).",
            ),
            Section(
                "ekf_reference.loops:LoopClosureParams",
                "`EKFConfig.loop_closure` (`None` by default; Victoria Park's profile sets "
                "`LoopClosureParams()`).",
            ),
        ),
    ),
    (
        "Association and map matching",
        (
            Section(
                "mapfuse_core.matching:AssociationConfig",
                "`EKFConfig.data_association` and `GraphOptions.data_association`: one set of "
                "settings for every estimator ([Method §4.1](method.md#41-association-settings)).",
            ),
            Section(
                "mapfuse_core.matching.ccda:CCDAParams",
                "`AssociationConfig.ccda`: the match with the known map "
                "([Method §5.1](method.md#51-matching-ccda)). `AssociationConfig()` uses "
                "`CCDAParams(min_pairings=8)`.",
            ),
        ),
    ),
    (
        "The factor graph",
        (
            Section(
                "mapfuse.estimators.graph:GraphRunOptions",
                "The `batch`, `isam2` and `fixedlag` estimators' options.",
            ),
            Section(
                "mapfuse_graph.options:GraphOptions",
                "`GraphRunOptions.graph`: what shapes the graph "
                "([Method §7](method.md#7-the-factor-graph-mirror)).",
            ),
            Section(
                "mapfuse_graph.isam2:ISAM2Options",
                "`GraphRunOptions.isam2`: iSAM2, also the fixed-lag smoother's.",
            ),
            Section(
                "mapfuse_graph.fixedlag:FixedLagOptions",
                "`GraphRunOptions.fixedlag` ([Method §7.1](method.md#71-fixed-lag-smoothing)).",
            ),
            Section(
                "mapfuse_graph.batch:LMOptions",
                "`GraphRunOptions.lm`: batch Levenberg–Marquardt (`None`: these defaults).",
            ),
        ),
    ),
    (
        "Extraction and change detection",
        (
            Section(
                "mapfuse_core.perception.extraction:ExtractionParams",
                "The feature extractor (a scenario's `[extraction]`, `CarmenOptions.extraction`); "
                '`ExtractionParams.profile("indoor_sick")` is the indoor profile '
                "([real data](real-data.md#the-indoor_sick-extraction-profile)).",
            ),
            Section(
                "mapfuse_core.changes:ChangeParams",
                "Change detection ([change detection](change-detection.md)); `mapfuse changes` "
                "sets `level` and the scenario's laser.",
            ),
        ),
    ),
    (
        "Real-data loaders",
        (
            Section(
                "mapfuse_core.data.datasets:CarparkOptions",
                "`load_carpark(data_dir, options)` ([real data](real-data.md#acfr-car-park-"
                "acfr_carpark)).",
            ),
            Section(
                "mapfuse_core.data.datasets:VictoriaParkOptions",
                "`load_victoria_park(data_dir, options)` ([real data](real-data.md#the-"
                "calibration)).",
            ),
            Section(
                "mapfuse_core.data.datasets:CarGeometry",
                "`CarparkOptions.geometry`, `VictoriaParkOptions.geometry`: the ACFR utility car "
                "([real data](real-data.md#the-car)).",
            ),
            Section(
                "mapfuse_core.data.datasets:OdometryNoise",
                "`CarparkOptions.odometry_noise` (`CARPARK_ODOMETRY_NOISE`), "
                "`VictoriaParkOptions.odometry_noise` (`VICTORIA_PARK_ODOMETRY_NOISE`): the "
                "dead-reckoning errors of the ACFR car. The table gives the class's defaults; "
                "the loaders' own are in their rows above.",
            ),
            Section(
                "mapfuse_core.data.datasets:CarmenOptions",
                "`load_carmen(path, options)` ([real data](real-data.md#carmen-indoor-logs)).",
            ),
            Section(
                "mapfuse_core.data.datasets:IncrementNoise",
                "`CarmenOptions.odometry_noise`: the odometry model of a CARMEN log.",
            ),
            Section(
                "mapfuse_core.data.datasets:FloorPlanParams",
                "`build_floor_plan(log, params)`: a CARMEN log's floor-plan known map "
                "([real data](real-data.md#floor-plan-as-known-map)).",
            ),
        ),
    ),
)

_R = "results/"
#: ``Class.field`` → Markdown link(s) to the measurements behind its default.
EVIDENCE: dict[str, str] = {
    "EKFConfig.local_map_steps": "`benchmarks/bench_ekf.py --sweep`; "
    f"[Victoria Park]({_R}victoria-park.md#ekf-ekf)",
    "EKFConfig.local_map_heading_sigma_rad": f"[CARMEN]({_R}carmen.md"
    "#the-ekfs-own-part-its-linearisation-over-a-local-map)",
    "EKFConfig.odometry_linearisation": f"[CARMEN]({_R}carmen.md"
    "#the-cause-the-update-linearised-at-the-measured-increment), "
    f"[EKF options]({_R}ekf-options.md#ekfconfigodometry_linearisation)",
    "EKFConfig.min_obs_to_join": f"[EKF options]({_R}ekf-options.md#ekfconfigmin_obs_to_join), "
    f"[Victoria Park]({_R}victoria-park.md#ekf-ekf)",
    "EKFConfig.tentative_min_sightings": f"[EKF options]({_R}ekf-options.md"
    "#ekfconfigtentative_min_sightings)",
    "EKFConfig.tentative_window_steps": f"[EKF options]({_R}ekf-options.md"
    "#ekfconfigtentative_min_sightings)",
    "EKFConfig.carry_seen_steps": f"[EKF options]({_R}ekf-options.md#ekfconfigcarry_seen_steps), "
    f"[known gaps]({_R}known-gaps.md#maximum-error-seeds-2-and-4)",
    "EKFConfig.loop_closure": f"[Victoria Park]({_R}victoria-park.md#ekf-ekf), "
    f"[calibration]({_R}victoria-park-calibration.md)",
    "EKFConfig.join_circle_sigma_m": f"[Victoria Park]({_R}victoria-park.md#ekf-ekf)",
    "EKFConfig.known_map_gating": f"[changes]({_R}changes.md"
    "#fusion-that-does-not-trust-a-wrong-map-the-known-map-gate), "
    f"[paper preset]({_R}ekf-paper-preset.md#measured-paper-against-the-default)",
    "EKFConfig.anchor_watch": f"[CCDA]({_R}ccda.md#after-fusion-the-anchor-watch)",
    "EKFConfig.anchor_entry": f"[paper preset]({_R}ekf-paper-preset.md#the-papers-three-forms)",
    "EKFConfig.known_map_in_local_maps": f"[paper preset]({_R}ekf-paper-preset.md"
    "#the-papers-three-forms)",
    "EKFConfig.line_tie_residual_at": f"[paper preset]({_R}ekf-paper-preset.md"
    f"#the-papers-three-forms), [models]({_R}models.md)",
    "KnownGatingParams.level": f"[changes]({_R}changes.md"
    "#fusion-that-does-not-trust-a-wrong-map-the-known-map-gate)",
    "KnownGatingParams.window": f"[changes]({_R}changes.md"
    "#fusion-that-does-not-trust-a-wrong-map-the-known-map-gate)",
    "LoopClosureParams.inlier_m": f"[calibration]({_R}victoria-park-calibration.md)",
    "AssociationConfig.method": f"[CARMEN]({_R}carmen.md#why-the-pose-nees-is-far-above-3)",
    "AssociationConfig.line_gap_m": f"[CARMEN]({_R}carmen.md#the-association-profile)",
    "AssociationConfig.known_wall_ends": f"[association]({_R}association.md"
    "#a-segment-lies-within-its-known-wall)",
    "AssociationConfig.map_method": f"[association]({_R}association.md"
    "#joins-joint-compatibility-and-ambiguous-features)",
    "AssociationConfig.map_ambiguity": f"[association]({_R}association.md"
    "#joins-joint-compatibility-and-ambiguous-features)",
    "AssociationConfig.ambiguity": f"[CARMEN]({_R}carmen.md#ambiguous-measurements)",
    "AssociationConfig.one_observation_per_line": f"[association]({_R}association.md"
    "#one-segment-per-scan-or-every-segment)",
    "AssociationConfig.ccda": f"[association]({_R}association.md#eight-ccda-pairings), "
    f"[paper preset]({_R}ekf-paper-preset.md#measured-paper-against-the-default)",
    "AssociationConfig.min_obs_for_matching": f"[paper preset]({_R}ekf-paper-preset.md"
    "#measured-paper-against-the-default)",
    "AssociationConfig.anchor_prior_sigma": f"[known gaps]({_R}known-gaps.md#forty-seeds)",
    "AssociationConfig.match_joint_test": f"[CCDA]({_R}ccda.md"
    "#a-drifted-map-the-joint-test-before-fusion), "
    f"[campaigns]({_R}montecarlo.md#c-generated-worlds-at-the-full-600-m-20-worlds)",
    "AssociationConfig.match_pairing_test": f"[CCDA]({_R}ccda.md"
    "#a-drifted-map-the-joint-test-before-fusion), "
    f"[changed worlds]({_R}changes-worlds.md)",
    "AssociationConfig.match_exclusions": f"[CCDA]({_R}ccda.md"
    "#a-drifted-map-the-joint-test-before-fusion), "
    f"[changed worlds]({_R}changes-worlds.md)",
    "CCDAParams.min_pairings": f"[association]({_R}association.md#eight-ccda-pairings)",
    "CCDAParams.redundant_pairings": f"[paper preset]({_R}ekf-paper-preset.md"
    "#measured-paper-against-the-default)",
    "CCDAParams.ambiguity_margin": f"[CCDA]({_R}ccda.md#evidence-that-repetition-cannot-fool)",
    "CCDAParams.rival_fraction": f"[CCDA]({_R}ccda.md#evidence-that-repetition-cannot-fool)",
    "CCDAParams.max_clique_work": f"[CCDA]({_R}ccda.md#bounded-search)",
    "CCDAParams.max_edges": f"[CCDA]({_R}ccda.md#bounded-search)",
    "CCDAParams.extent_margin_m": f"[CCDA]({_R}ccda.md#measured-hostile-worlds), "
    f"[CARMEN]({_R}carmen.md#the-association-profile)",
    "CCDAParams.unique_partners": f"[CCDA]({_R}ccda.md#ambiguous-partners)",
    "CCDAParams.var_floor_m": f"[CCDA]({_R}ccda.md#bounded-search)",
    "CCDAParams.var_floor_rad": f"[CCDA]({_R}ccda.md#bounded-search)",
    "GraphRunOptions.split_circles_where_exact": f"[Victoria Park]({_R}victoria-park.md"
    "#graph-backends-batch-isam2)",
    "GraphOptions.split_circles": f"[EKF options]({_R}ekf-options.md#graphoptionssplit_circles)",
    "ISAM2Options.relinearize_threshold": f"[performance]({_R}performance.md"
    "#looser-thresholds-with-a-final-gaussnewton-step)",
    "ISAM2Options.relinearize_skip": f"[performance]({_R}performance.md"
    "#isam2-on-sparse-worlds-benchmarksbench_isam2_sparsepy)",
    "ISAM2Options.partial_relinearization_check": f"[performance]({_R}performance.md"
    f"#the-partial-relinearisation-check), [fixed lag]({_R}fixedlag.md)",
    "ISAM2Options.final_updates": f"[fixed lag]({_R}fixedlag.md"
    "#agreement-loop600-seed-0-first-300-steps-fusion-truth-association)",
    "ISAM2Options.final_gauss_newton": f"[performance]({_R}performance.md"
    "#looser-thresholds-with-a-final-gaussnewton-step)",
    "ISAM2Options.final_marginals": f"[performance]({_R}performance.md"
    "#gtsam-from-python-mapfuse_graphbatchpy-mapfuse_graphisam2py)",
    "FixedLagOptions.lag_s": f"[fixed lag]({_R}fixedlag.md#the-spectrum)",
    "FixedLagOptions.landmarks": f"[fixed lag]({_R}fixedlag.md)",
    "ExtractionParams.occluded_end_margin": f"[extraction]({_R}extraction.md)",
    "ExtractionParams.min_circle_snr": f"[extraction]({_R}extraction.md), "
    f"[campaigns]({_R}montecarlo.md#a-the-papers-regime-loop600-sparse-40-seeds)",
    "ExtractionParams.wall_roughness_m": f"[CARMEN]({_R}carmen.md"
    "#the-indoor_sick-profiles-model-error-terms)",
    "ExtractionParams.line_model_sigma_m": f"[CARMEN]({_R}carmen.md"
    "#the-indoor_sick-profiles-model-error-terms)",
    "ExtractionParams.line_model_sigma_rad": f"[CARMEN]({_R}carmen.md"
    "#the-indoor_sick-profiles-model-error-terms)",
    "ChangeParams.level": f"[changes]({_R}changes.md#measurements)",
    "ChangeParams.min_scans": f"[changes]({_R}changes.md"
    "#missing-where-a-feature-would-have-been-extracted)",
    "ChangeParams.laser": f"[changes]({_R}changes.md"
    "#missing-where-a-feature-would-have-been-extracted)",
    "ChangeParams.missing_radius_sigmas": f"[changes]({_R}changes.md#measurements)",
    "ChangeParams.link_unviewed_lines": f"[changes]({_R}changes.md#measurements)",
    "ChangeParams.link_min_scans": f"[changes]({_R}changes.md"
    "#linking-after-a-brief-view-and-a-walls-length)",
    "ChangeParams.link_unviewed_circles": f"[changes]({_R}changes.md"
    "#linking-after-a-brief-view-and-a-walls-length)",
    "ChangeParams.free_space": f"[changes]({_R}changes.md"
    "#missing-where-the-laser-saw-through-the-surveyed-place)",
    "ChangeParams.relocalize": f"[changed worlds]({_R}changes-worlds.md"
    "#the-filters-poses-before-the-match-re-placed)",
    "ChangeParams.filter_estimates": f"[changed worlds]({_R}changes-worlds.md"
    f"#the-filters-poses-before-the-match-re-placed), [CARMEN]({_R}carmen.md"
    "#change-detection-against-the-floor-plan)",
    "ChangeParams.min_beams_circle": f"[changes]({_R}changes.md#car-park-real-data)",
    "CarparkOptions.pole_radius_m": f"[car park]({_R}carpark.md)",
    "CarparkOptions.sigma_range_m": f"[car park]({_R}carpark.md)",
    "CarparkOptions.sigma_bearing_rad": f"[car park]({_R}carpark.md)",
    "CarparkOptions.odometry_noise": f"[car park]({_R}carpark.md)",
    "CarparkOptions.laser_time_offset_s": f"[car park]({_R}carpark.md)",
    "CarparkOptions.bearing_offset_rad": f"[car park]({_R}carpark.md)",
    "VictoriaParkOptions.odometry_noise": f"[calibration]({_R}victoria-park-calibration.md"
    "#why-a-sideways-slip)",
    "VictoriaParkOptions.bearing_offset_rad": f"[calibration]({_R}victoria-park-calibration.md"
    "#why-a-sideways-slip)",
    "VictoriaParkOptions.steering_offset_rad": f"[calibration]({_R}victoria-park-calibration.md"
    "#the-tracking-fit)",
    "VictoriaParkOptions.speed_scale": f"[calibration]({_R}victoria-park-calibration.md"
    "#the-speed-scale)",
    "VictoriaParkOptions.detection_time_offset_s": f"[calibration]({_R}"
    "victoria-park-calibration.md#the-tracking-fit)",
    "CarmenOptions.extraction": f"[CARMEN]({_R}carmen.md"
    "#the-indoor_sick-profiles-model-error-terms)",
    "CarmenOptions.line_model_error": f"[CARMEN]({_R}carmen.md"
    "#line-model-error-estimated-from-each-log)",
    "CarmenOptions.line_model_gate": f"[CARMEN]({_R}carmen.md"
    "#gates-on-each-observations-error-alone)",
    "CarmenOptions.line_model_shape": f"[CARMEN]({_R}carmen.md"
    "#a-lateral-term-falling-with-the-segments-length)",
    "IncrementNoise.trans_frac": f"[CARMEN]({_R}carmen.md#odometry-evidence-on-the-seven-logs)",
    "FloorPlanParams.min_parallel_separation_m": f"[CARMEN]({_R}carmen.md#measured-figures)",
}

HEADER = """\
# Configuration

Every estimator takes one options dataclass; its no-argument instance holds the defaults.
`EKFConfig` is the `ekf` estimator's, `GraphRunOptions` the graph backends' (`batch`,
`isam2`, `fixedlag`); their fields hold the other dataclasses below. A run starts from
the defaults, changed by a dataset's profile (`mapfuse/profiles.py`: Victoria Park and
the CARMEN logs, [real data](real-data.md)), and then by the caller's overrides, field
by field ([Python](python.md#options)):

```python
mf.run(log, "ekf", local_map_steps=80, data_association={"gate_prob": 0.99})
mf.run(log, "isam2", isam2={"relinearize_skip": 1}, fixedlag={"lag_s": 10.0})
```

On the command line a few fields have options of their own (`--association`,
`--robust`, `--level`; [command line](cli.md)). For each field: its meaning (the first
sentence of its docstring, which says more), its default, and the measurements behind
the default where there are any (the results pages). *(choice)* marks a point the
paper leaves open ([Method](method.md)).

This page is generated from the dataclasses by `PYTHONPATH=. python
docs/tools/config_reference.py`; `tests/test_docs_pages.py` fails when it is out of date.
"""


def _load(target: str) -> type:
    module, name = target.split(":")
    cls = getattr(importlib.import_module(module), name)
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{target} is not a dataclass")
    return cls


def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of ``cls`` (the string statement after it)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    out: dict[str, str] = {}
    for node, after in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            out[node.target.id] = after.value.value
    return out


_ROLE = re.compile(r":(?:attr|class|func|meth|data|mod|obj):`(~?)([^`]+)`")


def _role(m: re.Match[str]) -> str:
    """A Sphinx cross-reference as code: ``~`` keeps the last component only."""
    name = m.group(2)
    return f"`{name.rsplit('.', 1)[-1] if m.group(1) else name}`"


def _markdown(rst: str) -> str:
    """Docstring reStructuredText as one line of Markdown for a table cell."""
    text = _ROLE.sub(_role, rst)
    text = text.replace("``", "`")
    text = " ".join(text.split())
    return _escape_pipes(text)


def _escape_pipes(text: str) -> str:
    """``|`` escaped outside code spans (a table cell ends there); inside them the table
    reader leaves it alone, and an escape would show."""
    parts = text.split("`")
    return "`".join(p if i % 2 else p.replace("|", "\\|") for i, p in enumerate(parts))


_SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z0-9*`(\"“])")


def first_sentence(doc: str) -> str:
    """The first sentence of a field's docstring, as Markdown."""
    text = _markdown(doc)
    for m in _SENTENCE_END.finditer(text):
        head = text[: m.start()]
        if head.endswith(("e.g.", "i.e.", "cf.", "vs.")) or head.count("`") % 2:
            continue
        if head.count("(") > head.count(")"):
            continue
        return head
    return text


def _number(x: float, name: str) -> str:
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    text = repr(x)
    if len(text) > 10:
        text = f"{x:.6g}"
    if name.endswith("_rad") and x and math.isfinite(x):
        text += f" ({math.degrees(x):.3g}°)"
    return text


def _plain(value: Any, name: str) -> str:
    """A value inside a dataclass's default: numbers shortened, angles in degrees too."""
    if isinstance(value, float) and not isinstance(value, bool):
        return _number(value, name)
    return repr(value)


def _value(value: Any, name: str) -> str:
    """A default as Markdown code."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        try:
            base = cls()
        except TypeError:
            base = None
        diff = [
            f"{f.name}={_plain(getattr(value, f.name), f.name)}"
            for f in dataclasses.fields(cls)
            if base is None or getattr(value, f.name) != getattr(base, f.name)
        ]
        return f"`{cls.__name__}({', '.join(diff)})`"
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return f"`{value!r}`"
    if isinstance(value, float):
        return f"`{_number(value, name)}`"
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return "`(" + ", ".join(_number(v, "") for v in value) + ")`"
    return f"`{value!r}`"


def section(sec: Section) -> str:
    """One dataclass: a heading, where it is used and its field table."""
    cls = _load(sec.target)
    docs = field_docs(cls)
    default = cls()
    lines = [
        f"### `{cls.__name__}`",
        "",
        f"`{sec.target.replace(':', '.')}`. {sec.where}",
        "",
        "| field | meaning | default | evidence |",
        "|---|---|---|---|",
    ]
    for f in dataclasses.fields(cls):
        doc = docs.get(f.name)
        if doc is None:
            raise ValueError(f"{cls.__name__}.{f.name} has no docstring")
        evidence = EVIDENCE.get(f"{cls.__name__}.{f.name}", "–")
        value = _value(getattr(default, f.name), f.name)
        lines.append(f"| `{f.name}` | {first_sentence(doc)} | {value} | {evidence} |")
    return "\n".join(lines) + "\n"


def covered() -> list[type]:
    """Every dataclass the page documents, in page order."""
    return [_load(s.target) for _, group in SECTIONS for s in group]


def page() -> str:
    """The whole page."""
    parts = [HEADER]
    for title, group in SECTIONS:
        parts.append(f"## {title}\n")
        parts.extend(section(s) for s in group)
    fields = {f"{c.__name__}.{f.name}" for c in covered() for f in dataclasses.fields(c)}
    stale = sorted(set(EVIDENCE) - fields)
    if stale:
        raise ValueError(f"evidence for fields that do not exist: {', '.join(stale)}")
    return "\n".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the page is out of date")
    args = ap.parse_args()
    text = page()
    if args.check:
        if PAGE.read_text() != text:
            print(f"{PAGE} is out of date: run {Path(__file__).relative_to(ROOT)}", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

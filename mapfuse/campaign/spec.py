"""What a campaign runs: :class:`CampaignSpec`, and the syntax of ``--seeds``,
``--fusion`` and ``--world-per-run``.

A campaign directory holds the spec it was started with (``campaign.json``); resuming
with a different spec is refused, except for the seed list, which may grow.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ["FUSION_CHOICES", "CampaignSpec", "parse_fusion", "parse_seeds", "parse_world_args"]

#: ``--fusion`` values and the fusion settings they run.
FUSION_CHOICES: Mapping[str, tuple[bool, ...]] = {
    "on": (True,),
    "off": (False,),
    "both": (True, False),
}


def parse_seeds(text: str) -> tuple[int, ...]:
    """Seeds from ``"0-39"``, ``"0,3,7"`` or a mix (``"0-4,10"``); distinct, in order."""
    seeds: list[int] = []
    for part in str(text).split(","):
        lo, dash, hi = (s.strip() for s in part.partition("-"))
        if not lo.isdigit() or (dash and not hi.isdigit()):
            raise ValueError(f"seeds must look like 0-39 or 0,3,7; got {text!r}")
        if dash and int(hi) < int(lo):
            raise ValueError(f"seed range {part.strip()!r} runs backwards")
        seeds += list(range(int(lo), int(hi) + 1)) if dash else [int(lo)]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds repeat in {text!r}")
    return tuple(seeds)


def parse_fusion(text: str) -> tuple[bool, ...]:
    """The fusion settings of ``--fusion on|off|both``."""
    if text not in FUSION_CHOICES:
        raise ValueError(f"--fusion must be one of {', '.join(FUSION_CHOICES)}, got {text!r}")
    return FUSION_CHOICES[text]


_KIND_NAMES = {int: "an integer", float: "a number", str: "text"}


def parse_world_args(text: str) -> dict[str, Any]:
    """``--world-per-run`` arguments, ``"walls=6,trees=40,shape=figure8"``, as the
    generator's keywords (numbers converted; the seed comes from each run)."""
    from mapfuse_core.sim.worldgen import WorldParams

    out: dict[str, Any] = {}
    if not text.strip():
        return out
    fields = WorldParams.__dataclass_fields__
    for part in text.split(","):
        key, eq, value = (s.strip() for s in part.partition("="))
        key = key.replace("-", "_")
        if not eq or not key:
            raise ValueError(f"--world-per-run: expected key=value items, got {part!r}")
        if key == "seed":
            raise ValueError("--world-per-run: the seed of each world is the run's seed")
        if key not in fields:
            raise ValueError(
                f"--world-per-run: unknown generator argument {key!r} "
                f"(known: {', '.join(k for k in fields if k != 'seed')})"
            )
        kind = type(getattr(WorldParams(seed=0), key))
        try:
            out[key] = kind(value)
        except ValueError:
            raise ValueError(
                f"--world-per-run: {key} must be "
                f"{_KIND_NAMES.get(kind, kind.__name__)}, got {value!r}"
            ) from None
    WorldParams(seed=0, **out)  # validates the values now, not on the workers
    return out


@dataclass(frozen=True)
class CampaignSpec:
    """Everything that decides a campaign's per-run results (not how it is executed)."""

    scenario: str
    """Built-in scenario name or TOML path that every run simulates (the base of the
    generated worlds with :attr:`world`)."""
    seeds: tuple[int, ...]
    """Run seeds; a run's every random draw derives from its seed alone."""
    estimators: tuple[str, ...] = ("ekf",)
    """Registered estimator names run on every log."""
    fusions: tuple[bool, ...] = (True, False)
    """Fusion settings run for every estimator."""
    steps: int | None = None
    """Only the first ``steps`` steps of every log (``None``: all)."""
    world: Mapping[str, Any] | None = None
    """Generator arguments (:func:`mapfuse_core.sim.worldgen.generate_scenario` keywords
    other than ``seed``) to draw a new world for every run from its seed, or ``None``
    to simulate :attr:`scenario` as it is."""
    plugins: tuple[str, ...] = ()
    """``module:attribute`` estimators each worker registers before running (for
    estimators that are not entry points of the installed package)."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    """Free-form labels stored with the spec (never read by the runs)."""

    def __post_init__(self) -> None:
        if not self.seeds:
            raise ValueError("a campaign needs at least one seed")
        if any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in self.seeds):
            raise ValueError(f"seeds must be integers >= 0, got {list(self.seeds)}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError("seeds must be distinct")
        if not self.estimators or len(set(self.estimators)) != len(self.estimators):
            raise ValueError(f"estimators must be distinct names, got {list(self.estimators)}")
        if not self.fusions or len(set(self.fusions)) != len(self.fusions):
            raise ValueError(f"fusions must be distinct booleans, got {list(self.fusions)}")
        if self.steps is not None and (
            isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1
        ):
            raise ValueError(f"steps must be an integer >= 1, got {self.steps!r}")

    def to_json(self) -> dict[str, Any]:
        """The ``campaign.json`` object."""
        return {
            "scenario": self.scenario,
            "seeds": list(self.seeds),
            "estimators": list(self.estimators),
            "fusions": list(self.fusions),
            "steps": self.steps,
            "world": None if self.world is None else dict(self.world),
            "plugins": list(self.plugins),
            "extra": dict(self.extra),
        }

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> CampaignSpec:
        """The inverse of :meth:`to_json`."""
        return cls(
            scenario=str(obj["scenario"]),
            seeds=tuple(int(s) for s in obj["seeds"]),
            estimators=tuple(obj["estimators"]),
            fusions=tuple(bool(f) for f in obj["fusions"]),
            steps=obj.get("steps"),
            world=obj.get("world"),
            plugins=tuple(obj.get("plugins", ())),
            extra=dict(obj.get("extra", {})),
        )

    def same_runs(self, other: CampaignSpec) -> list[str]:
        """Fields other than the seeds in which ``other`` differs (empty: compatible)."""
        a, b = self.to_json(), other.to_json()
        return [k for k in a if k not in ("seeds", "extra") and a[k] != b[k]]

    def with_seeds(self, seeds: Sequence[int]) -> CampaignSpec:
        """This spec over ``seeds``."""
        return CampaignSpec(
            scenario=self.scenario,
            seeds=tuple(seeds),
            estimators=self.estimators,
            fusions=self.fusions,
            steps=self.steps,
            world=self.world,
            plugins=self.plugins,
            extra=self.extra,
        )

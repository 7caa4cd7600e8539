"""The campaign directory: ``campaign.json``, ``runs.jsonl`` and ``arrays/``.

* ``campaign.json`` — the :class:`~mapfuse.campaign.spec.CampaignSpec`;
* ``runs.jsonl`` — the per-run table, one JSON object per run × estimator × fusion
  setting (``pandas.read_json(path, lines=True)`` loads it); a run's rows are
  appended together, in one write, as the run finishes;
* ``arrays/seed_NNNNNN.npz`` — the run's per-step arrays
  (:func:`mapfuse.campaign.task.array_key`), written before its rows.

A run is finished when its rows are in ``runs.jsonl``; a campaign killed mid-write
leaves at most a truncated last line, which :class:`CampaignStore` drops on opening.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapfuse.campaign.spec import CampaignSpec
from mapfuse.campaign.task import RunOutcome

__all__ = ["CampaignStore"]

SPEC_FILE = "campaign.json"
TABLE_FILE = "runs.jsonl"
ARRAY_DIR = "arrays"


def _read_rows(path: Path) -> list[dict[str, Any]]:
    """Rows of ``path``; a truncated last line (a killed write) is dropped from the file."""
    if not path.exists():
        return []
    text = path.read_text()
    lines = text.split("\n")
    rows: list[dict[str, Any]] = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as e:
            if any(x.strip() for x in lines[n:]):
                raise ValueError(f"{path}:{n}: not a JSON line ({e})") from None
            good = "\n".join(lines[: n - 1])
            path.write_text(good + "\n" if good else "")
            break
    return rows


@dataclass(frozen=True)
class CampaignStore:
    """A campaign directory (created when missing)."""

    root: Path
    """The directory."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @classmethod
    def open(cls, root: str | Path, spec: CampaignSpec) -> CampaignStore:
        """The directory ``root`` for ``spec``: new, or one made for the same runs
        (only the seeds may differ; the stored spec takes the union of both)."""
        store = cls(Path(root))
        store.root.mkdir(parents=True, exist_ok=True)
        path = store.root / SPEC_FILE
        if path.exists():
            old = CampaignSpec.from_json(json.loads(path.read_text()))
            diff = old.same_runs(spec)
            if diff:
                raise ValueError(
                    f"{store.root} holds a campaign with other {', '.join(diff)} "
                    f"({', '.join(f'{k}={old.to_json()[k]!r}' for k in diff)}); use another --out"
                )
            seeds = tuple(dict.fromkeys([*old.seeds, *spec.seeds]))
            spec = spec.with_seeds(seeds)
        path.write_text(json.dumps(spec.to_json(), indent=1) + "\n")
        (store.root / ARRAY_DIR).mkdir(exist_ok=True)
        return store

    @property
    def table_path(self) -> Path:
        """``runs.jsonl``."""
        return self.root / TABLE_FILE

    def spec(self) -> CampaignSpec:
        """The stored spec."""
        return CampaignSpec.from_json(json.loads((self.root / SPEC_FILE).read_text()))

    def array_path(self, seed: int) -> Path:
        """The ``.npz`` of run ``seed``."""
        return self.root / ARRAY_DIR / f"seed_{seed:06d}.npz"

    def rows(self) -> list[dict[str, Any]]:
        """Every stored row, in the order runs finished."""
        return _read_rows(self.table_path)

    def finished(self, rows_per_run: int) -> set[int]:
        """Seeds whose ``rows_per_run`` rows are all stored."""
        count: dict[int, int] = {}
        for r in self.rows():
            count[r["seed"]] = count.get(r["seed"], 0) + 1
        return {s for s, c in count.items() if c >= rows_per_run}

    def drop(self, seeds: Iterable[int]) -> None:
        """Forget the rows and arrays of ``seeds`` (to run them again)."""
        drop = set(seeds)
        keep = [r for r in self.rows() if r["seed"] not in drop]
        tmp = self.table_path.with_suffix(".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in keep))
        os.replace(tmp, self.table_path)
        for s in drop:
            self.array_path(s).unlink(missing_ok=True)

    def write(self, outcome: RunOutcome) -> None:
        """Store one finished run: its arrays, then (one write) its rows."""
        path = self.array_path(outcome.seed)
        tmp = path.with_name(path.stem + ".tmp.npz")
        arrays: dict[str, Any] = dict(outcome.arrays)
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
        wall = round(outcome.wall_time_s, 3)
        text = "".join(json.dumps({**r, "wall_s": wall}) + "\n" for r in outcome.rows)
        with self.table_path.open("a") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    def arrays(self, seed: int) -> dict[str, np.ndarray]:
        """The per-step arrays of run ``seed`` (empty when none were stored)."""
        path = self.array_path(seed)
        if not path.exists():
            return {}
        with np.load(path) as z:
            return {k: z[k] for k in z.files}

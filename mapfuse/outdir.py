"""Output folders and files: refuse to mix a new run's files with another's, or clear them.

A folder holding files mapfuse writes (:func:`is_mapfuse_file`) is refused unless
``force``; with ``force`` those files are removed first, so no stale file (an
``associations.npz`` of an earlier run that decided its own associations, a
``trajectory_filtered.tum`` of another backend) stays beside the new ones.  Other
files in the folder are left alone.  An output *file* (a baseline, a generated world)
that exists is refused unless ``force``.

The checks (:func:`check_output_dir`, :func:`check_output_file`) change nothing, so a
command makes them before any work and prepares the folder
(:func:`prepare_output_dir`) only when it has something to write.
"""

from __future__ import annotations

import fnmatch
import os
import shutil
import tempfile
from pathlib import Path

__all__ = [
    "MAPFUSE_NAMES",
    "OutputFolderError",
    "check_output_dir",
    "check_output_file",
    "is_mapfuse_file",
    "prepare_output_dir",
]

#: Names (glob patterns) of the files and folders the mapfuse commands write.
MAPFUSE_NAMES: tuple[str, ...] = (
    # simulate
    "log.npz",
    "world.png",
    # run
    "metrics.json",
    "*.tum",
    "errors.png",
    "gps_errors.png",
    "gps_trajectory.png",
    "gps_trajectories.png",
    "associations.npz",
    "graph.g2o",
    "graph.json",
    # compare
    "comparison.json",
    "beside.json",
    "report.md",
    "fig*.png",
    "nees.png",
    "timing.png",
    "runs",
    # montecarlo
    "campaign.json",
    "runs.jsonl",
    "arrays",
    "anees.png",
    "rmse.png",
    "max_error.png",
    # spectrum
    "spectrum.json",
    "spectrum.png",
    # changes
    "changes.json",
    "changes.png",
)


class OutputFolderError(ValueError):
    """An output folder or file that cannot be used as asked."""


def is_mapfuse_file(path: Path) -> bool:
    """Whether ``path`` (an entry of an output folder) is one mapfuse writes."""
    return any(fnmatch.fnmatch(path.name, pat) for pat in MAPFUSE_NAMES)


def _ours(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if is_mapfuse_file(p)) if path.is_dir() else []


def _check_creatable(path: Path, flag: str) -> None:
    """``path`` (missing) can be made: its nearest existing ancestor is a writable
    folder."""
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputFolderError(f"{flag} {path} is not writable: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFolderError(f"{flag} {path} is not writable: {parent} is read-only")


def _probe(path: Path, flag: str) -> None:
    try:
        with tempfile.NamedTemporaryFile(dir=path, prefix=".mapfuse-probe-"):
            pass
    except OSError as exc:
        raise OutputFolderError(f"{flag} {path} is not writable: {exc.strerror or exc}") from None


def check_output_dir(out: str | Path, force: bool = False) -> Path:
    """Whether ``out`` can take a run's files, changing nothing; an
    :class:`OutputFolderError` for a file, an unwritable folder, or (without ``force``)
    a folder holding another run's files.  Returns the folder's path."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise OutputFolderError(f"--out {path} is a file, not a folder")
    ours = _ours(path)
    if ours and not force:
        names = ", ".join(p.name for p in ours[:5]) + (", ..." if len(ours) > 5 else "")
        raise OutputFolderError(
            f"--out {path} holds another run's files ({names}); "
            "pass --force to replace them, or choose another folder"
        )
    if path.is_dir():
        _probe(path, "--out")
    else:
        _check_creatable(path, "--out")
    return path


def prepare_output_dir(out: str | Path, force: bool = False) -> Path:
    """Make ``out`` ready for a run's files (:func:`check_output_dir`, then created, and
    with ``force`` cleared of mapfuse's files), or raise :class:`OutputFolderError`.
    Returns the folder."""
    path = check_output_dir(out, force)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputFolderError(f"--out {path} is not writable: {exc.strerror or exc}") from None
    _probe(path, "--out")
    for p in _ours(path):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return path


def check_output_file(out: str | Path, force: bool = False) -> Path:
    """Whether the file ``out`` can be written, changing nothing: not a folder, in a
    writable (or creatable) folder, and (without ``force``) not there yet.  Returns its
    path."""
    path = Path(out)
    if path.is_dir():
        raise OutputFolderError(f"--out {path} is a folder; give a file name")
    if path.exists() and not force:
        raise OutputFolderError(
            f"--out {path} exists; pass --force to replace it, or choose another file"
        )
    if path.parent.is_dir():
        try:
            _probe(path.parent, "--out")
        except OutputFolderError as exc:
            raise OutputFolderError(f"--out {path}: {exc}") from None
    else:
        _check_creatable(path, "--out")
    return path

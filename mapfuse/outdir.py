"""Output folders: refuse to mix a new run's files with another's, or clear them.

A folder holding files mapfuse writes (:func:`is_mapfuse_file`) is refused unless
``force``; with ``force`` those files are removed first, so no stale file (an
``associations.npz`` of an earlier run that decided its own associations, a
``trajectory_filtered.tum`` of another backend) stays beside the new ones.  Other
files in the folder are left alone.  The folder is checked writable before any work.
"""

from __future__ import annotations

import fnmatch
import shutil
import tempfile
from pathlib import Path

__all__ = ["OutputFolderError", "is_mapfuse_file", "prepare_output_dir"]

#: Names (glob patterns) of the files and folders the mapfuse commands write.
MAPFUSE_NAMES: tuple[str, ...] = (
    "log.npz",
    "world.png",
    "metrics.json",
    "*.tum",
    "errors.png",
    "gps_errors.png",
    "gps_trajectory.png",
    "gps_trajectories.png",
    "associations.npz",
    "comparison.json",
    "report.md",
    "fig*.png",
    "nees.png",
    "timing.png",
    "runs",
    "graph.g2o",
    "graph.json",
)


class OutputFolderError(ValueError):
    """An output folder that cannot be used as asked."""


def is_mapfuse_file(path: Path) -> bool:
    """Whether ``path`` (an entry of an output folder) is one mapfuse writes."""
    return any(fnmatch.fnmatch(path.name, pat) for pat in MAPFUSE_NAMES)


def prepare_output_dir(out: str | Path, force: bool = False) -> Path:
    """Make ``out`` ready for a run's files, or raise :class:`OutputFolderError`.

    Refuses a file, an unwritable folder, and (without ``force``) a folder holding
    another run's files; with ``force`` removes those files.  Returns the folder.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise OutputFolderError(f"--out {path} is a file, not a folder")
    ours = sorted(p for p in path.iterdir() if is_mapfuse_file(p)) if path.is_dir() else []
    if ours and not force:
        names = ", ".join(p.name for p in ours[:5]) + (", ..." if len(ours) > 5 else "")
        raise OutputFolderError(
            f"--out {path} holds another run's files ({names}); "
            "pass --force to replace them, or choose another folder"
        )
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".mapfuse-probe-"):
            pass
    except OSError as exc:
        raise OutputFolderError(f"--out {path} is not writable: {exc.strerror or exc}") from None
    for p in ours:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return path

"""Reading the dataset files: MATLAB variables and numeric text tables, checked.

Each reader returns finite float arrays of the expected shape or raises
:class:`~mapfuse_core.data.datasets.common.DatasetError` naming the file, the variable and
what is wrong with it.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from mapfuse_core.data.datasets.common import DatasetError
from mapfuse_core.geometry.se2 import FloatArray


def _require_file(path: Path) -> None:
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")


def load_mat(path: Path) -> dict[str, Any]:
    """The variables of a MATLAB file."""
    _require_file(path)
    try:
        return dict(scipy.io.loadmat(str(path)))
    except Exception as exc:  # scipy raises several unrelated types for damaged files
        raise DatasetError(f"{path}: cannot be read as a MATLAB file ({exc})") from exc


def _mat_array(mat: dict[str, Any], path: Path, name: str) -> np.ndarray:
    if name not in mat:
        raise DatasetError(f"{path}: missing variable '{name}'")
    arr = mat[name]
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "iuf":
        kind = getattr(arr, "dtype", type(arr).__name__)
        raise DatasetError(f"{path}: variable '{name}' is not a real numeric array ({kind})")
    return arr


def _check_finite_array(arr: FloatArray, path: Path, name: str) -> None:
    if arr.size and not np.all(np.isfinite(arr)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        raise DatasetError(f"{path}: '{name}' has a non-finite value ({arr[idx]}) at index {idx}")


def mat_vector(
    mat: dict[str, Any], path: Path, name: str, *, length: int | None = None
) -> FloatArray:
    """A 1×N, N×1 or N variable as a finite float vector of the given length."""
    arr = _mat_array(mat, path, name)
    if arr.ndim > 2 or (arr.ndim == 2 and min(arr.shape) > 1) or arr.size == 0:
        raise DatasetError(f"{path}: '{name}' has shape {arr.shape}, expected a non-empty vector")
    vec = np.asarray(arr, dtype=np.float64).reshape(-1)
    if length is not None and vec.shape[0] != length:
        raise DatasetError(f"{path}: '{name}' has {vec.shape[0]} values, expected {length}")
    _check_finite_array(vec, path, name)
    return vec


def mat_matrix(
    mat: dict[str, Any], path: Path, name: str, shape: tuple[int | None, int]
) -> FloatArray:
    """A finite float matrix of the given shape (``None`` rows: any number)."""
    arr = _mat_array(mat, path, name)
    rows, cols = shape
    if arr.ndim != 2 or arr.shape[1] != cols or (rows is not None and arr.shape[0] != rows):
        want = f"{'N' if rows is None else rows}×{cols}"
        raise DatasetError(f"{path}: '{name}' has shape {arr.shape}, expected {want}")
    out = np.asarray(arr, dtype=np.float64)
    _check_finite_array(out, path, name)
    return out


def read_table(path: Path, n_cols: int, columns: str) -> FloatArray:
    """A whitespace-separated numeric text file of ``n_cols`` columns, all finite."""
    _require_file(path)
    try:
        # An empty file only warns in numpy; it is reported below as an error instead.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a numeric table of {columns} ({exc})") from exc
    if table.shape[0] == 0:
        raise DatasetError(f"{path}: no rows")
    if table.shape[1] != n_cols:
        raise DatasetError(f"{path}: {table.shape[1]} columns, expected {n_cols} ({columns})")
    _check_finite_array(table, path, columns)
    return table


def check_increasing(t: FloatArray, path: Path, name: str, *, strict: bool) -> None:
    """Raise :class:`DatasetError` unless ``t`` increases (strictly when ``strict``)."""
    d = np.diff(t)
    bad = np.nonzero(d <= 0.0 if strict else d < 0.0)[0]
    if bad.size:
        i = int(bad[0])
        how = "strictly increasing" if strict else "non-decreasing"
        raise DatasetError(
            f"{path}: '{name}' must be {how}; value {i + 1} ({t[i + 1]}) follows {t[i]}"
        )

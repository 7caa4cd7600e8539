"""Where the real datasets live: a directory given by the caller, else ``$MAPFUSE_DATA``.

One rule for the library (:func:`mapfuse.load`'s ``data``) and the command line
(``--data``), so that a notebook and a shell that set the variable read the same files.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Environment variable naming the data directory of the real datasets.
DATA_ENV = "MAPFUSE_DATA"


def data_dir(given: str | Path | None, source: str, name: str) -> str:
    """The data directory for dataset ``source``: ``given``, else ``$MAPFUSE_DATA``.

    ``name`` is the caller's name of the argument, for the messages: a keyword
    (``"data"``, written ``data=DIR``) or an option (``"--data"``, written ``--data
    DIR``).  Raises ``ValueError`` when neither names a directory (an empty ``given``
    included), or when the one used is not a directory.
    """
    spelling = f"{name} DIR" if name.startswith("-") else f"{name}=DIR"
    if given is not None and not str(given):
        raise ValueError(f"{name} is empty: give the data directory ({spelling})")
    directory = str(given) if given is not None else os.environ.get(DATA_ENV) or None
    if directory is None:
        raise ValueError(f"dataset {source!r} needs a data directory ({spelling} or ${DATA_ENV})")
    if not Path(directory).is_dir():
        where = name if given is not None else f"${DATA_ENV}"
        raise ValueError(f"{where} {directory} is not a directory")
    return directory

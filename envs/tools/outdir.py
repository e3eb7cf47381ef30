"""Output folders of every command: checked before any work, written atomically.

Rules (DESIGN.md, "Contracts"): an ``--out`` that is a file, or a folder that is not empty, is refused before
anything runs unless ``overwrite`` is set; results are written into a temporary sibling folder
(``.NAME.partial-XXXX``) that is renamed to ``NAME`` only when the run completes, so an interrupted or failed
run (an exception, Ctrl-C) leaves no folder that looks complete. With ``overwrite`` the previous folder is
swapped out only at that final rename, so it survives a run that fails.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutDirError(ValueError):
    """An output folder that cannot be used (the message names it and says why)."""


def check_out_dir(path: Path | str, overwrite: bool = False, option: str = "--out") -> Path:
    """Check that ``path`` can receive a run's output; returns it as a :class:`Path`.

    Args:
        path: The output folder (it need not exist).
        overwrite: Allow a non-empty existing folder (it is replaced when the run completes).
        option: How the caller names the folder in messages (``--out``).

    Raises:
        OutDirError: ``path`` is an existing file, a non-empty folder without ``overwrite``, or its parent
            is a file.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutDirError(f"{option} {path} is an existing file, not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OutDirError(
            f"{option} {path} is not empty (an earlier run?); choose a new folder or pass --overwrite"
        )
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutDirError(f"{option} {path}: {parent} is a file, not a folder")
            break
    return path


@contextmanager
def atomic_out_dir(path: Path | str, overwrite: bool = False, option: str = "--out") -> Iterator[Path]:
    """Yield a temporary sibling folder of ``path``; rename it to ``path`` when the block completes.

    On any exception (``KeyboardInterrupt`` included) the temporary folder is removed and ``path`` is left as
    it was. ``path`` is checked (:func:`check_out_dir`) before the block runs and again before the rename.

    Raises:
        OutDirError: See :func:`check_out_dir`.
    """
    final = check_out_dir(path, overwrite, option)
    parent = final.absolute().parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.partial-", dir=parent))
    try:
        yield tmp
        check_out_dir(final, overwrite, option)
        if final.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-", dir=parent))
            os.replace(final, old / "previous")
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

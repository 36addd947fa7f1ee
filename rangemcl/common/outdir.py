"""The output policy of every command: what it does with an output that exists.

Commands that write a folder (:func:`check_output`, :func:`output_folder`):

* A folder that holds results is refused in one line naming ``--overwrite``; a folder that holds files
  which are not this command's results is refused even with ``--overwrite`` (nothing of the user's is
  deleted by a mistyped ``--out``).
* ``--overwrite`` replaces the folder whole: the earlier run's folder is set aside (renamed to a hidden
  sibling ``.NAME.replaced``) and the new run writes into an empty one, so no plot or table of the
  earlier run stays beside the new results; the earlier folder is deleted when the new run succeeds
  and put back when it fails.
* A run that fails or is refused leaves nothing it created: the folder (and any parent it had to make)
  is removed again, unless the run has kept results by then (``keep_if``: e.g. the frames a localization
  wrote before it was interrupted).

Commands that write files (a town, a PNG, a mesh, a sweep's scan: :func:`check_output_files`,
:func:`output_files`), the same rules:

* A file that exists is refused in one line naming ``--overwrite``; with it, the file is replaced when the
  new one is written whole (the writers write atomically), so a failed run leaves the earlier file.
* A path that is a folder, or lies under a file or in a folder that cannot be written, is refused.
* Folders missing above the files are made (as for output folders), and removed again with the files this
  run made when the run fails.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rangemcl.errors import InputError

MAP_MARKERS = ("map.yaml", "tiles.json", "mesh.ply", "tiles.npz")  # a map folder (formats 2 and 1)
RESULT_MARKERS = ("frames.csv", "summary.json", "config.yaml", "estimate_kitti.txt")  # localize's results


def _clear(folder: Path) -> None:
    """Remove everything inside ``folder``."""
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


def check_output(path: str | os.PathLike, *, overwrite: bool, kind: str, markers: Iterable[str]) -> Path:
    """Refuse ``path`` as an output folder of a ``kind`` (e.g. "localization results") unless it is
    absent, empty, or holds such results (one of ``markers``) and ``overwrite`` is given; an
    :class:`InputError` names the folder and the way out. Changes nothing."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: exists and is not a folder (choose another --out)")
    if path.is_dir() and any(path.iterdir()):
        ours = any((path / m).exists() for m in markers)
        if not ours:
            raise InputError(
                f"{path}: folder is not empty and holds no {kind}; refusing to write into it "
                "(choose another --out)"
            )
        if not overwrite:
            raise InputError(f"{path}: holds {kind} of an earlier run (give --overwrite to replace them)")
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{path}: cannot write here ({probe} is not a writable folder)")
    return path


@contextmanager
def output_folder(
    path: str | os.PathLike,
    *,
    overwrite: bool,
    kind: str,
    markers: Iterable[str],
    keep_if: Callable[[Path], bool] | None = None,
) -> Iterator[Path]:
    """Claim ``path`` under the policy (:func:`check_output`), empty and existing, for the ``with`` block.
    If the block raises (any exception, Ctrl-C included) and ``keep_if(path)`` is not true, everything the
    run created is removed again; the exception propagates."""
    path = check_output(path, overwrite=overwrite, kind=kind, markers=markers)
    made = None  # the outermost folder this run creates
    probe = path
    while not probe.exists():
        made = probe
        probe = probe.parent
    backup = None  # the earlier results that --overwrite replaces, set aside until the run succeeds
    if made is None and any(path.iterdir()):
        backup = path.with_name(f".{path.name}.replaced")
        if backup.exists():
            shutil.rmtree(backup)  # left by a run that was killed outright
        path.rename(backup)
    path.mkdir(parents=True, exist_ok=True)
    try:
        yield path
    except BaseException:
        if keep_if is not None and keep_if(path):
            if backup is not None:
                shutil.rmtree(backup, ignore_errors=True)
        else:
            if made is not None:
                shutil.rmtree(made, ignore_errors=True)
            elif backup is not None:
                shutil.rmtree(path, ignore_errors=True)
                backup.rename(path)  # the earlier results come back
            elif path.is_dir():
                _clear(path)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)


def has_frames(path: Path) -> bool:
    """A localization folder whose ``frames.csv`` holds at least one frame (results to keep)."""
    f = path / "frames.csv"
    try:
        with f.open() as fh:
            return sum(1 for _ in zip(range(2), fh, strict=False)) >= 2
    except OSError:
        return False


def check_output_files(
    paths: Iterable[str | os.PathLike], *, overwrite: bool, what: str, option: str = "--out"
) -> list[Path]:
    """Refuse to write the files ``paths`` (what one run of a command writes; ``what`` names them in the
    message, e.g. "the town") when one of them exists, unless ``overwrite``; refuse a path that is a
    folder, lies under a file, or whose folder cannot be written, whatever ``overwrite``. An
    :class:`InputError` names the path and the way out. Changes nothing."""
    out = [Path(p) for p in paths]
    for p in out:
        if p.is_dir():
            raise InputError(f"{option} {p}: is a folder (give a file name)")
        probe = p.parent
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        if not probe.is_dir():
            raise InputError(f"{option} {p}: cannot be written ({probe} is a file)")
        if not os.access(probe, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
            raise InputError(f"{option} {p}: cannot write here ({probe} is not a writable folder)")
    existing = [p for p in out if p.exists()]
    if existing and not overwrite:
        raise InputError(f"{existing[0]}: exists (give --overwrite to replace {what})")
    return out


@contextmanager
def output_files(
    paths: Iterable[str | os.PathLike],
    *,
    overwrite: bool,
    what: str,
    option: str = "--out",
    also: Iterable[str | os.PathLike] = (),
) -> Iterator[list[Path]]:
    """Claim the files ``paths`` under the policy (:func:`check_output_files`) for the ``with`` block:
    the folders missing above them are made. If the block raises (Ctrl-C included), the files it created
    (``paths`` and ``also``: files it may write beside them that are never refused, e.g. a shared include)
    and the folders made for them are removed again; files that existed stay as they are (their writers
    replace them atomically). The exception propagates."""
    out = check_output_files(paths, overwrite=overwrite, what=what, option=option)
    extra = [Path(p) for p in also]
    existed = {p for p in [*out, *extra] if p.exists()}
    made: list[Path] = []  # the outermost folders this run creates
    for p in out:
        probe, top = p.parent, None
        while not probe.exists():
            top, probe = probe, probe.parent
        if top is not None:
            made.append(top)
            p.parent.mkdir(parents=True, exist_ok=True)
    try:
        yield out
    except BaseException:
        for p in [*out, *extra]:
            if p not in existed and (p.is_file() or p.is_symlink()):
                p.unlink(missing_ok=True)
        for folder in made:
            shutil.rmtree(folder, ignore_errors=True)
        raise

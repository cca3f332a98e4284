"""The one atomic writer and the checks of output paths.

Every file and folder the programs write appears complete or not at all: it is written under a temporary name
beside its place and renamed into place when complete; on failure the temporary is removed and what was there
stays (:func:`atomic_file`, :func:`swapped_folder`; :func:`atomic_folder` adds the manifest of an output folder).
The temporary names all match :data:`TEMP_NAME`, so that a message never shows one (:func:`shown_path`).

An output folder holds the manifest :data:`MANIFEST_NAME` (which tool wrote which entries); only such a folder,
holding nothing else, is ever replaced (:func:`check_replaceable`).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import yaml

from lrfcal.errors import InputError

#: The file every output folder of this project holds: which tool wrote it and the entries it wrote. Only a
#: folder with this file and no other entries may be replaced (``--overwrite``).
MANIFEST_NAME = ".lrf-calib-output.yaml"

#: the names of the tools' own temporary files and folders: a file being written (``.NAME.<random>.tmp``), a
#: folder being written or moved aside (``.NAME.tmp-<random>``, ``.NAME.old-<random>``), the write probe of
#: :func:`check_writable` and the figures' scratch folder (lrfcal.commands.calibrate)
TEMP_NAME = re.compile(r"^\.(figures-|lrf-write-probe-|.+\.(tmp|old)-|.+\.tmp$)")


def current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def shown_path(filename: object) -> str:
    """``filename`` as a message may show it: a temporary path of the tool's own is replaced by the folder it was
    being written in (a user never made it and cannot act on its name)."""
    path = str(filename)
    parent, _, name = path.rpartition(os.sep)
    return (parent or ".") if TEMP_NAME.match(name) else path


# --- the atomic writer ----------------------------------------------------------------------------------------

@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Write one file atomically: yields a new empty temporary file beside ``path`` (its folder made) to write
    into; when the block completes the file gets the usual mode (0666 less the umask) and is renamed onto
    ``path``; when it fails it is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; give the file the usual mode
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | Path, chunks: Iterable[bytes | memoryview]) -> Path:
    """Write ``chunks`` one after the other into the file ``path``, atomically (:func:`atomic_file`)."""
    path = Path(path)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        for c in chunks:
            f.write(c)
    return path


@contextmanager
def swapped_folder(out: str | Path, *, make: bool = True) -> Iterator[Path]:
    """Write one folder atomically: yields a temporary folder beside ``out`` (:func:`make_temp_beside`); when the
    block completes it is renamed into place (:func:`swap_into_place`); when it fails it is removed and ``out`` is
    left as it was.

    With ``make=False``, for a writer that makes the folder itself and names files after it (rosbags' Writer names
    a bag's data file ``<folder name>.mcap``): yields the free path ``<temporary folder>/<out's name>``, so that
    what the writer names after the folder carries the final name, never a temporary one."""
    out = Path(out)
    tmp = make_temp_beside(out)
    try:
        if make:
            yield tmp
            swap_into_place(tmp, out)
        else:
            yield tmp / out.name
            swap_into_place(tmp / out.name, out)
            tmp.rmdir()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_folder(out: str | Path, tool: str) -> Iterator[Path]:
    """Build an output folder atomically: yields a new temporary folder beside ``out`` to write into; when the
    block completes, the manifest (which ``tool`` wrote what) is added and the folder renamed into place
    (:func:`swap_into_place`); when it fails, the temporary folder is removed and ``out`` is left as it was."""
    with swapped_folder(out) as tmp:
        yield tmp
        write_manifest(tmp, tool)


def make_temp_beside(out: Path) -> Path:
    """A new hidden temporary folder next to ``out`` (created with its parents; usual permissions).

    Raises:
        InputError: the parent folder cannot be created or written.
    """
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700; give the folder the usual mode
    except OSError as e:
        raise InputError(f"{out}: cannot write the output folder here ({e.strerror or e})") from None
    return tmp


def swap_into_place(tmp: Path, out: Path) -> None:
    """Rename the finished folder tmp to out, replacing an existing out (moved aside, then deleted)."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    old.rmdir()
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --- the manifest of an output folder -------------------------------------------------------------------------

def write_manifest(folder: Path, tool: str) -> Path:
    """Write :data:`MANIFEST_NAME` into ``folder``, listing its current top-level entries (written by ``tool``)."""
    folder = Path(folder)
    entries = sorted(p.name for p in folder.iterdir() if p.name != MANIFEST_NAME)
    text = yaml.safe_dump({"written_by": tool, "entries": entries}, sort_keys=False)
    path = folder / MANIFEST_NAME
    path.write_text(text, encoding="utf-8")
    return path


def _manifest_entries(folder: Path) -> set[str] | None:
    """The entries a manifest in ``folder`` lists, or None when there is no readable manifest."""
    try:
        data = yaml.safe_load((folder / MANIFEST_NAME).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("entries"), list):
        return None
    return {str(e) for e in data["entries"]}


# --- checks of output paths, before any work ------------------------------------------------------------------

def check_replaceable(out_dir: str | Path, overwrite: bool) -> Path:
    """Refuse an output folder that must not be written: return ``out_dir`` as a Path when it may be.

    Allowed: a missing or empty folder; with ``overwrite``, a folder that this project wrote (it holds the
    manifest :data:`MANIFEST_NAME`) and that holds nothing else than the entries the manifest lists. Anything
    else raises :class:`InputError` naming the folder and, where there are any, the files we did not write.
    """
    out = Path(out_dir)
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise InputError(f"{out}: output exists and is not a folder")
    if not out.is_dir():
        return out
    try:
        present = sorted(p.name for p in out.iterdir())
    except OSError as e:
        raise InputError(f"{out}: cannot read the output folder ({e.strerror})") from None
    if not present:
        return out
    # what --overwrite would be refused for is said already without it: one message, one fix
    listed = _manifest_entries(out)
    if listed is None:
        raise InputError(f"{out}: output folder exists, is not empty and was not written by lrf-calib (no "
                         f"{MANIFEST_NAME}), so it is never replaced, not even with --overwrite: choose another "
                         "output folder")
    foreign = [n for n in present if n != MANIFEST_NAME and n not in listed]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise InputError(f"{out}: output folder exists and holds files lrf-calib did not write ({shown}), so it is "
                         "never replaced, not even with --overwrite: move them away or choose another output folder")
    if not overwrite:
        raise InputError(f"{out}: output folder exists (written by lrf-calib): use --overwrite to replace it")
    return out


def check_writable(out: str | Path) -> Path:
    """Refuse an output path that cannot be created, before any work: its nearest existing ancestor must be a
    folder in which a folder can be made (tried with an empty hidden folder, removed at once).

    Raises:
        InputError: naming the path and the ancestor that blocks it.
    """
    out = Path(out)
    anc = out.absolute().parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"{out}: cannot write the output folder here ({anc} is not a folder)")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write the output folder here ({anc} is not writable)")
    try:  # permissions do not tell everything (root, /proc, read-only mounts, full disks): try it, before the work
        os.rmdir(tempfile.mkdtemp(prefix=".lrf-write-probe-", dir=anc))
    except OSError as e:
        raise InputError(f"{out}: cannot write the output folder here ({anc}: {e.strerror or e})") from None
    return out


def _resolved(p: str | Path) -> Path:
    return Path(p).expanduser().resolve()


def check_no_overlap(outputs: Mapping[str, str | Path | None], inputs: Mapping[str, str | Path | None],
                     may_nest_in: tuple[str, ...] = ()) -> None:
    """Refuse outputs that are, contain or lie inside an input.

    Args:
        outputs, inputs: ``{label: path}``; None entries are skipped.
        may_nest_in: labels of input folders an output may lie inside (e.g. the recording folder, where
            ``REC/calibration`` touches no input file), though never be or contain.
    Raises:
        InputError: naming the output, the input and how they overlap.
    """
    for o_label, o in outputs.items():
        if o is None:
            continue
        ro = _resolved(o)
        for i_label, i in inputs.items():
            if i is None:
                continue
            ri = _resolved(i)
            if ro == ri:
                how = "is"
            elif ro in ri.parents:
                how = "contains"
            elif ri in ro.parents and i_label not in may_nest_in:
                how = "lies inside"
            else:
                continue
            raise InputError(f"{o}: {o_label} {how} the {i_label} {i}: outputs never overlap inputs (nor each "
                             "other); choose another path")


def check_outputs(inputs: list[Path], outputs: list[Path]) -> None:
    """Refuse outputs that equal, contain or lie inside an input, or each other (``lrfcal reproject`` and
    ``lrfcal convert``: unlabelled paths)."""
    ins = [p.resolve() for p in inputs]
    outs = [p.resolve() for p in outputs]
    for o in outs:
        for i in ins:
            if o == i or i.is_relative_to(o) or o.is_relative_to(i):
                raise InputError(f"{o}: output overlaps the input {i}; choose another output path")
    if len(set(outs)) != len(outs):
        raise InputError(f"outputs: the same path given twice ({', '.join(map(str, outputs))})")


__all__ = [
    "MANIFEST_NAME", "TEMP_NAME", "atomic_file", "atomic_folder", "check_no_overlap", "check_outputs",
    "check_replaceable", "check_writable", "current_umask", "make_temp_beside", "shown_path", "swap_into_place",
    "swapped_folder", "write_bytes_atomic", "write_manifest",
]

"""Files: atomic writes (a hidden temporary file renamed into place), early checks that a
path can be written, the field as ``.npy`` and the JSON report.

Every writer of the package goes through :func:`atomic_path`, so an error or Ctrl-C never
leaves a half-written file, and writes the same bytes for the same input; and the command line
runs each command in :func:`run_outputs`, so an error or Ctrl-C after some outputs are in place
removes them too (no mesh left without its report).
"""
from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError

__all__ = ["PiecewiseDeflate", "atomic_path", "check_format", "check_writable", "folder_of", "mark_written", "new_temp",
           "discard", "place", "remove_quietly", "run_outputs", "written_path",
           "write_field", "write_json"]

#: planes of about this many voxels are converted and written at a time (.npy)
WRITE_VOXELS = 1 << 18


#: bytes of a stream deflated as one piece (on one thread)
DEFLATE_PIECE = 1 << 22
_WINDOW = 1 << 15


def _deflate_piece(data: bytes, zdict: bytes, level: int, final: bool) -> bytes:
    import zlib

    c = (zlib.compressobj(level, zlib.DEFLATED, -15, zdict=zdict) if zdict
         else zlib.compressobj(level, zlib.DEFLATED, -15))
    return c.compress(data) + c.flush(zlib.Z_FINISH if final else zlib.Z_SYNC_FLUSH)


class PiecewiseDeflate:
    """A raw deflate stream made of fixed pieces deflated on the thread pool (pigz's scheme).

    The data are cut every :data:`DEFLATE_PIECE` bytes; each piece is deflated with the
    previous piece's last 32 KiB as its dictionary and ends on a sync flush, the last on
    the stream's end, so the pieces joined are one valid deflate stream. The cuts depend on
    the data alone, so the bytes are the same whatever the threads. zlib frees the
    interpreter while it deflates, so the pieces run on every core. It has the ``compress``
    and ``flush`` of a ``zlib.compressobj(level, zlib.DEFLATED, -15)``, which
    :mod:`zipfile` calls too.

    Parameters
    ----------
    level : int
        zlib's compression level, 1 (fastest) to 9.
    """

    def __init__(self, level: int):
        from collections import deque

        self.level = int(level)
        self.buffer = bytearray()
        self.tail = b""
        self.pending = deque()

    def _submit(self, data: bytes, final: bool) -> None:
        from ..run.threads import submit

        zdict, self.tail = self.tail, data[-_WINDOW:]
        self.pending.append(submit(_deflate_piece, data, zdict, self.level, final))

    def compress(self, data) -> bytes:
        """Deflate more data; returns the stream's bytes finished so far (maybe none)."""
        from ..run.threads import count

        self.buffer += data
        done = []
        while len(self.buffer) >= DEFLATE_PIECE:
            self._submit(bytes(self.buffer[:DEFLATE_PIECE]), False)
            del self.buffer[:DEFLATE_PIECE]
            # at most twice the threads' pieces in flight: bounded memory
            while len(self.pending) > 2 * count():
                done.append(self.pending.popleft().result())
        return b"".join(done)

    def flush(self) -> bytes:
        """The rest of the stream, to its end."""
        self._submit(bytes(self.buffer), True)
        self.buffer = bytearray()
        done = [job.result() for job in self.pending]
        self.pending.clear()
        return b"".join(done)


def folder_of(path) -> Path:
    return Path(os.path.abspath(os.fspath(path))).parent


def os_reason(exc: OSError, option: str = "-o") -> str:
    """Why `exc` stops a write, and the fix through `option` (the command-line option that names the file)."""
    if isinstance(exc, FileNotFoundError):
        return f"folder does not exist; pick an existing folder with {option}"
    if isinstance(exc, NotADirectoryError):
        return f"not a folder; pick an existing folder with {option}"
    if isinstance(exc, PermissionError):
        return f"permission denied; pick a folder you can write to with {option}"
    reason = (exc.strerror or type(exc).__name__).lower()
    return f"{reason}; pick another folder or file name with {option}"


def new_temp(final: Path) -> Path:
    """Create an empty hidden temporary file beside `final` (same extension, ``.nii.gz`` whole); raise OSError."""
    from .formats import suffix

    folder = folder_of(final)
    # the whole extension, as written (.nii.gz, not .gz: the writers read the format off the name)
    ext = final.name[len(final.name) - len(suffix(final)):] if suffix(final) else ""
    for _ in range(100):
        tmp = folder / f".{final.name}.tmp-{secrets.token_hex(4)}{ext}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"no free temporary name beside {final}")


def remove_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.remove(path)


#: the outputs the current run (:func:`run_outputs`) has put in place so far; None outside a run
_WRITTEN: list | None = None
#: the current run's finished outputs still under their temporary names, (temporary, final) in the order
#: they were finished: put in place when the run ends (:func:`place`)
_PENDING: list | None = None


def mark_written(path) -> None:
    """Note an output just put in place (renamed from its temporary name): :func:`run_outputs` removes
    it if the run then fails or is interrupted. Nothing outside a run."""
    if _WRITTEN is not None:
        _WRITTEN.append(Path(path))


def _remove_any(path: Path) -> None:
    import shutil

    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        remove_quietly(path)


def _put_in_place(tmp: Path, final: Path) -> None:
    """Rename `tmp` (a file, or a folder) onto `final` (for a folder: an empty folder there is replaced);
    ScaffoldError when the system refuses."""
    try:
        if tmp.is_dir() and final.is_dir():
            final.rmdir()  # empty (the writers check it): os.replace does not replace a folder
        os.replace(tmp, final)
    except OSError as exc:
        _remove_any(tmp)
        raise ScaffoldError(f"cannot write to {final}: {os_reason(exc)}") from None
    mark_written(final)


def place(tmp, final) -> None:
    """Put a finished output, written under the temporary name `tmp`, in place as `final`.

    Outside a run, at once. Inside :func:`run_outputs`, when the run ends: every output of a run appears
    together, after its last is finished, so that a run killed outright (SIGKILL, the system's out-of-memory
    killer, during the measures after the mesh) leaves its hidden temporary files, never a mesh without
    its report."""
    tmp, final = Path(tmp), Path(final)
    if _PENDING is None:
        _put_in_place(tmp, final)
    else:
        _PENDING.append((tmp, final))


def discard(final) -> None:
    """Remove an intermediate file a run wrote as an output (a staged mesh read back into another format):
    under its temporary name while it waits for the run's end (:func:`place`), or in place. The run's end
    then has nothing to put there."""
    final = Path(final)
    if _PENDING is not None:
        for entry in [e for e in _PENDING if e[1] == final]:
            _PENDING.remove(entry)
            _remove_any(entry[0])
    remove_quietly(final)


def written_path(final) -> Path:
    """Where the output `final` can be read now: its temporary name while it waits for the run's end
    (:func:`place`), else `final` itself."""
    path = Path(final)
    pending = {target: tmp for tmp, target in _PENDING or []}
    # a writer may write inside another's temporary file (a field export into the run's), itself waiting
    while path in pending:
        path = pending.pop(path)
    return path


@contextlib.contextmanager
def run_outputs():
    """Context manager: a run's outputs are all left, or none. A run writes several files one after
    another (the mesh, then the measures of it, then the JSON report): each stays under its temporary
    name until the run ends (:func:`place`), and an error or an interrupt removes them, and anything
    the run has put in place (:func:`mark_written`), so that "no output written" is true and no mesh is
    left without its report."""
    global _WRITTEN, _PENDING
    outer = _WRITTEN, _PENDING
    _WRITTEN, _PENDING = [], []
    try:
        yield
        while _PENDING:
            _put_in_place(*_PENDING.pop(0))
    except BaseException:
        for tmp, _ in _PENDING:
            _remove_any(tmp)
        for path in reversed(_WRITTEN):
            _remove_any(path)
        raise
    finally:
        _WRITTEN, _PENDING = outer


def check_writable(path, *, formats=None, option: str = "-o") -> Path:
    """Fail early, with a one-line fix, if `path` cannot be written.

    Call it before any long computation. It creates and removes a temporary file in
    the target folder, and leaves nothing behind.

    Parameters
    ----------
    path : str or os.PathLike
        File to be written.
    formats : sequence of str, optional
        Allowed extensions (e.g. :data:`MESH_FORMATS`), lower case with the dot.
    option : str
        The command-line option that names `path`, as the error's fix names it.

    Returns
    -------
    pathlib.Path
        `path`, as given.

    Raises
    ------
    ScaffoldError
        The extension is not allowed, the folder does not exist, is not a folder or
        cannot be written to, or `path` is a folder.
    """
    final = Path(path)
    if formats is not None:
        check_format(final, formats)
    folder = folder_of(final)
    if not folder.exists():
        raise ScaffoldError(
            f"cannot write to {folder}: folder does not exist; pick an existing folder with {option}")
    if not folder.is_dir():
        raise ScaffoldError(f"cannot write to {folder}: not a folder; pick an existing folder with {option}")
    if final.is_dir():
        raise ScaffoldError(f"cannot write to {final}: it is a folder; give a file name with {option}")
    try:
        tmp = new_temp(final)
    except OSError as exc:
        raise ScaffoldError(f"cannot write to {folder}: {os_reason(exc, option)}") from None
    remove_quietly(tmp)
    return final


@contextlib.contextmanager
def atomic_path(path):
    """Context manager: a temporary path that becomes `path` only if the block succeeds.

    Yields a hidden file name in the same folder, ``.NAME.tmp-XXXXXXXX.EXT`` (the
    extension is kept for exporters that look at it; the file exists, empty). When
    the block exits normally the file is renamed onto `path` with :func:`os.replace`
    (atomic on one file system; inside :func:`run_outputs`, when the run ends: :func:`place`); when it raises, the temporary file is removed and
    `path` is left as it was.

    Raises
    ------
    ScaffoldError
        The folder does not exist or cannot be written to.
    """
    final = Path(path)
    if final.is_dir():
        raise ScaffoldError(f"cannot write to {final}: it is a folder; give a file name with -o")
    try:
        tmp = new_temp(final)
    except OSError as exc:
        raise ScaffoldError(f"cannot write to {folder_of(final)}: {os_reason(exc)}") from None
    try:
        yield tmp
    except BaseException:
        remove_quietly(tmp)
        raise
    place(tmp, final)


def check_format(final: Path, formats) -> str:
    from .formats import suffix

    ext = suffix(final)
    if ext not in formats:
        raise ScaffoldError(f"cannot write {final}: unknown file type {ext or '(no extension)'!r}; "
                            f"use one of {', '.join(formats)}")
    return ext


def write_field(field, path) -> Path:
    """Write a field as a float32 ``.npy`` file, atomically.

    The array is converted slab by slab, so a float64 field is never copied whole.
    The bytes equal ``np.save(path, field.astype(np.float32))``.

    Parameters
    ----------
    field : ndarray, mm, or a field on disk (``.grid`` and ``.read(x0, x1)``, e.g. a
        :class:`~implicit_scaffold.run.tiles.FieldFile`)
    path : str or os.PathLike
        Must end in ``.npy``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ScaffoldError
        The extension is not ``.npy``, or the folder cannot be written to.
    """
    final = Path(path)
    check_format(final, (".npy",))
    if hasattr(field, "read"):  # a field on disk (tiles.FieldFile): read plane range by plane range
        shape, planes = tuple(field.grid.shape), field.read
    else:
        field = np.asarray(field)
        shape = tuple(field.shape)
        planes = lambda i0, i1: field[i0:i1]  # noqa: E731
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype("<f4")), "fortran_order": False, "shape": shape}
    with atomic_path(final) as tmp, open(tmp, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        if not shape:
            fh.write(field.astype("<f4").tobytes())
        else:
            per = int(np.prod(shape[1:], dtype=np.int64)) or 1
            step = max(1, WRITE_VOXELS // per)
            for i0 in range(0, shape[0], step):
                fh.write(np.ascontiguousarray(planes(i0, min(i0 + step, shape[0])), dtype="<f4").tobytes())
    return final


def _json_default(obj):
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write a {type(obj).__name__} to JSON")


def write_json(obj, path) -> Path:
    """Write `obj` as pretty JSON (2-space indent, sorted keys, final newline), atomically.

    NumPy scalars and arrays are written as numbers and lists, paths as strings.
    Non-finite floats are written as ``NaN``/``Infinity``, as :mod:`json` does.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ScaffoldError
        The folder cannot be written to.
    """
    final = Path(path)
    text = json.dumps(obj, indent=2, sort_keys=True, ensure_ascii=False, default=_json_default) + "\n"
    with atomic_path(final) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)
    return final

"""Every file a verb writes: its target checked before the work, then written whole or not at all.

A file goes to a temporary file in its target directory, is flushed and fsynced, renamed over the
target (``os.replace``) and the directory is fsynced; on any failure the temporary file is removed
and an earlier file at the target stays as it was. A :class:`Batch` stages several files (and the
removal of stale ones) and renames them only when all are written, so a failure midway leaves the
earlier set intact rather than a mix of new and old. An ``OSError`` becomes one
:class:`~maglev_ros.errors.UserError` line naming the path and the OS reason.

JSON goes out strict: a non-finite number (NaN, +-inf) is written as ``null``.
"""
from __future__ import annotations

import errno
import io
import json
import math
import os
import secrets
import tempfile
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable

from maglev_ros.errors import UserError

__all__ = ["Batch", "batch_or_new", "check_dir", "check_figure", "check_file", "check_parent",
           "finite_or_null", "fsync_dir", "json_text", "write_bytes", "write_json", "write_text"]

_TMP_SUFFIX = ".tmp"


# ------------------------------------------------------------------------------ strict JSON
def finite_or_null(obj: Any, default: Callable[[Any], Any] | None = None) -> Any:
    """``obj`` with every non-finite float replaced by None (dicts, lists and tuples walked).

    ``default`` converts objects JSON cannot encode (as ``json.dumps(default=...)``), and its
    result is walked too; other values are returned unchanged."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v, default) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v, default) for v in obj]
    if obj is None or isinstance(obj, (str, int)):
        return obj
    if default is not None:
        return finite_or_null(default(obj), default)
    return obj


def json_text(doc: Any, indent: int | None = 1, default: Callable[[Any], Any] | None = None) -> str:
    """Strict JSON text of ``doc`` (non-finite numbers as null, see :func:`finite_or_null`)."""
    return json.dumps(finite_or_null(doc, default), indent=indent, allow_nan=False)


# ------------------------------------------------------------------------- target checks
def _label(option: str | None, path) -> str:
    return f"{option} {path}" if option else str(path)


def _probe(directory: Path, option: str | None, path) -> None:
    """Create and remove a temporary file in ``directory``: the only reliable writability test
    (permission bits say nothing for root, a read-only mount or a full inode table)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".maglev-probe-", suffix=_TMP_SUFFIX, dir=directory)
    except OSError as exc:
        raise UserError(f"{_label(option, path)}: cannot write in {directory} "
                        f"({exc.strerror or exc})") from None
    os.close(fd)
    try:
        os.unlink(tmp)
    except OSError:
        pass


def check_parent(path, option: str | None = None) -> Path:
    """The directory that will hold ``path`` exists, is a directory and takes new files."""
    p = Path(path)
    if not str(path):
        raise UserError(f"{option or 'output'}: expected a path, got an empty string")
    parent = p.parent
    if not parent.exists():
        raise UserError(f"{_label(option, path)}: directory {parent} does not exist")
    if not parent.is_dir():
        raise UserError(f"{_label(option, path)}: {parent} is not a directory")
    _probe(parent, option, path)
    return p


def check_file(path, option: str | None = None) -> Path:
    """``path`` can be written as a file: not a directory, in an existing writable directory."""
    p = check_parent(path, option)
    if p.is_dir():
        raise UserError(f"{_label(option, path)}: is a directory; expected a file name")
    return p


def check_figure(path, option: str | None = None) -> Path:
    """:func:`check_file`, and a file name suffix matplotlib can write (none: png)."""
    p = check_file(path, option)
    fmt = p.suffix.lstrip(".").lower()
    if fmt:
        from matplotlib.backend_bases import FigureCanvasBase
        known = FigureCanvasBase.get_supported_filetypes()
        if fmt not in known:
            raise UserError(f"{_label(option, path)}: unknown figure format {p.suffix!r}; expected "
                            f"one of {', '.join('.' + k for k in sorted(known))}")
    return p


def check_dir(path, option: str | None = None) -> Path:
    """``path`` can be an output directory: an existing writable directory, or one that can be
    created (its nearest existing ancestor is a writable directory)."""
    if not str(path):
        raise UserError(f"{option or 'output'}: expected a directory, got an empty string")
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise UserError(f"{_label(option, path)}: is a file; expected a directory")
        _probe(p, option, path)
        return p
    anc = p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise UserError(f"{_label(option, path)}: cannot create the directory, {anc} is a file")
    _probe(anc, option, path)
    return p


# --------------------------------------------------------------------------------- writing
def fsync_dir(directory: Path) -> None:
    """Make a rename durable; filesystems that cannot fsync a directory are let be."""
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    try:
        fd = os.open(directory, flags)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF, errno.EACCES):
            raise
    finally:
        os.close(fd)


def _create_temp(target: Path) -> tuple[int, Path]:
    """A new hidden file beside ``target``, created with mode 0o666 so the umask applies as for a
    plain ``open(target, "w")`` (mkstemp's 0o600 would hide the output from other users)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}{_TMP_SUFFIX}")
        try:
            return os.open(tmp, flags, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(target))


class Batch:
    """Stage files, rename them all at the end; a context manager.

    Inside ``with Batch() as b:`` each ``b.write_*`` writes its temporary file at once (so a full
    disk is found before anything is replaced); leaving the block without an error renames them
    over their targets, removes what ``b.remove`` named and fsyncs the directories. Leaving it with
    an error removes the temporary files and the directories ``b.make_dir`` created; the targets
    are untouched."""

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path, str]] = []     # (tmp, target, label)
        self._remove: list[Path] = []
        self._made_dirs: list[Path] = []
        self.paths: list[Path] = []                        # targets, in the order written

    def __enter__(self) -> "Batch":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.commit()
        else:
            self.discard()
        return False

    # ------------------------------------------------------------------ staging
    def make_dir(self, path, option: str | None = None) -> Path:
        """Create the output directory ``path`` (and parents); removed again on failure if empty."""
        p = Path(path)
        missing = []
        q = p
        while not q.exists() and q != q.parent:
            missing.append(q)
            q = q.parent
        for d in reversed(missing):
            try:
                d.mkdir()
            except FileExistsError:
                continue
            except OSError as exc:
                raise UserError(f"{_label(option, path)}: cannot create directory {d} "
                                f"({exc.strerror or exc})") from None
            self._made_dirs.append(d)
        if not p.is_dir():
            raise UserError(f"{_label(option, path)}: is a file; expected a directory")
        return p

    def write_bytes(self, path, data: bytes, option: str | None = None) -> Path:
        target = Path(path)
        label = _label(option, path)
        if target.is_dir():
            raise UserError(f"{label}: is a directory; expected a file name")
        try:
            fd, tmp = _create_temp(target)
        except OSError as exc:
            raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            if target.is_file():       # an existing output keeps its mode
                os.chmod(tmp, target.stat().st_mode & 0o7777)
        except OSError as exc:
            _unlink(tmp)
            raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
        except BaseException:
            _unlink(tmp)
            raise
        self._staged.append((tmp, target, label))
        self.paths.append(target)
        return target

    def write_text(self, path, text: str, option: str | None = None) -> Path:
        return self.write_bytes(path, text.encode("utf-8"), option)

    def write_json(self, path, doc: Any, indent: int | None = 1,
                   default: Callable[[Any], Any] | None = None, option: str | None = None) -> Path:
        """Strict JSON (non-finite numbers as null)."""
        return self.write_text(path, json_text(doc, indent, default), option)

    def write_figure(self, path, fig, option: str | None = None, **savefig_kw) -> Path:
        """A matplotlib figure, in the format its file name says (png without a suffix)."""
        buf = io.BytesIO()
        fmt = Path(path).suffix.lstrip(".").lower() or None
        fig.savefig(buf, format=fmt, **savefig_kw)
        return self.write_bytes(path, buf.getvalue(), option)

    def remove(self, path) -> None:
        """Remove ``path`` at commit (a stale output this run does not replace)."""
        self._remove.append(Path(path))

    # ------------------------------------------------------------------ ending
    def commit(self) -> list[Path]:
        dirs = []
        staged, self._staged = self._staged, []
        for i, (tmp, target, label) in enumerate(staged):
            try:
                os.replace(tmp, target)
            except OSError as exc:
                for t, _, _ in staged[i:]:
                    _unlink(t)
                raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
            if target.parent not in dirs:
                dirs.append(target.parent)
        for p in self._remove:
            if p.is_file() or p.is_symlink():
                _unlink(p)
                if p.parent not in dirs:
                    dirs.append(p.parent)
        self._made_dirs = []
        for d in dirs:
            try:
                fsync_dir(d)
            except OSError as exc:
                raise UserError(f"{d}: cannot sync the directory after writing "
                                f"{', '.join(p.name for p in self.paths)} ({exc.strerror or exc})") from None
        return self.paths

    def discard(self) -> None:
        staged, self._staged = self._staged, []
        for tmp, _, _ in staged:
            _unlink(tmp)
        for d in reversed(self._made_dirs):
            try:
                d.rmdir()
            except OSError:
                pass
        self._made_dirs = []


def batch_or_new(batch: Batch | None):
    """``with batch_or_new(batch) as b:`` stages in the caller's batch, or in one of its own that
    commits at the end of the block (for writers usable alone or as part of a set)."""
    return nullcontext(batch) if batch is not None else Batch()


def _unlink(p: Path) -> None:
    try:
        os.unlink(p)
    except OSError:
        pass


# ------------------------------------------------------------------------ one-file writers
def write_bytes(path, data: bytes, option: str | None = None) -> Path:
    with Batch() as b:
        b.write_bytes(path, data, option)
    return Path(path)


def write_text(path, text: str, option: str | None = None) -> Path:
    with Batch() as b:
        b.write_text(path, text, option)
    return Path(path)


def write_json(path, doc: Any, indent: int | None = 1, default: Callable[[Any], Any] | None = None,
               option: str | None = None) -> Path:
    """Strict JSON (non-finite numbers as null), written atomically."""
    with Batch() as b:
        b.write_json(path, doc, indent, default, option)
    return Path(path)

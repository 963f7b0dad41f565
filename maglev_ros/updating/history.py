"""Durable store of accepted parameter updates: an append-only JSON-lines file, one record per update.

Writing: one writer per file, for the writer's lifetime (``fcntl.flock`` on the history itself,
taken by ``open_writer`` or the first ``append``; a second writer, in this or another process, is
refused with one line naming the file and the holder's pid). A record is ONE ``os.write`` of one
line ending in "\\n" on an O_APPEND descriptor, then ``fsync``: the file is never rewritten, an
append costs one line whatever the history's length, and a kill leaves every acknowledged record.
Revisions continue from the highest valid revision in the file (read under the lock) + 1.

Damage is never dropped silently. A line that is not UTF-8/JSON, not a record of this schema, or
has a non-finite number is skipped on read and listed in ``skipped``/``warnings``; the writer
copies it (with its line number) to the sibling ``<stem>.damaged.jsonl`` once. A torn last line
(no end of line: a crash mid-write or another tool) is copied there too and cut off the history,
so the next record never glues onto it; a last line that is a whole record missing only its "\\n"
is kept and terminated. The writer also removes the ``<name>.XXXXXXXX.tmp`` files that earlier
versions (whole-file rewrite + rename) left behind when killed.

A parameter value must be a finite number (the record is refused, naming the parameter, with a
``UserError``); other non-finite numbers (a std, provenance) are stored as null (unknown): JSON has
no NaN. Hand-written: sqlite would also do, but JSON lines stay readable with any tool.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import math
import os
import re
import time
from pathlib import Path
from typing import Any, Mapping

from maglev_ros.errors import UserError

SCHEMA = "maglev-param-history/1"
DAMAGED_SCHEMA = "maglev-param-history-damaged/1"


def line_key(metadata: Mapping[str, Any]) -> str:
    """Identity of a test line for the history: a hash of the metadata's ``line`` and ``design``
    blocks (the contract has no line id; parameters updated on one line never apply to another)."""
    ident = {"line": metadata.get("line"), "design": metadata.get("design")}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]


def damaged_path(path: str | os.PathLike) -> Path:
    """Where damaged lines of the history ``path`` are kept: ``<stem>.damaged.jsonl`` beside it."""
    path = Path(path)
    return path.with_name((path.stem if path.suffix == ".jsonl" else path.name) + ".damaged.jsonl")


class _NonFinite(ValueError):
    pass


def _reject_constant(name: str):
    raise _NonFinite(f"non-finite number {name} (JSON has none)")


def _is_finite_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def parse_record(raw: bytes) -> tuple[dict | None, str]:
    """One history line -> (record, "") or (None, why it is not a record)."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None, "not UTF-8 text"
    try:
        rec = json.loads(text, parse_constant=_reject_constant)
    except _NonFinite as exc:
        return None, str(exc)
    except ValueError as exc:
        return None, f"not JSON ({exc})"
    if not isinstance(rec, dict) or rec.get("schema") != SCHEMA:
        return None, f"not a history record (no \"schema\": \"{SCHEMA}\")"
    rev = rec.get("revision")
    if not isinstance(rev, int) or isinstance(rev, bool) or rev < 1:
        return None, f"field revision: expected a positive integer, got {rev!r}"
    params = rec.get("parameters")
    if not isinstance(params, dict):
        return None, "field parameters: expected an object"
    for name, p in params.items():
        if not isinstance(p, dict) or not _is_finite_number(p.get("value")):
            return None, f"parameter {name}: expected an object with a finite number \"value\""
    return rec, ""


def _finite_or_null(obj):
    """A JSON-ready copy: numpy scalars/arrays as Python values, non-finite floats as None."""
    if isinstance(obj, Mapping):
        return {str(k): _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_null(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):
        return _finite_or_null(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _holder_pid(fd: int) -> int | None:
    """The pid holding a flock on ``fd``'s file, from /proc/locks (Linux; None elsewhere)."""
    st = os.fstat(fd)
    want = (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
    try:
        with open("/proc/locks") as f:
            for row in f:
                parts = row.split()
                if len(parts) < 6 or parts[1] != "FLOCK":          # "->" rows are waiters
                    continue
                dev = parts[5].split(":")
                if len(dev) == 3 and (int(dev[0], 16), int(dev[1], 16), int(dev[2])) == want:
                    return int(parts[4])
    except (OSError, ValueError):
        return None
    return None


def _fsync_dir(directory: Path) -> None:
    dfd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


class ParameterHistory:
    """Accepted updates in ``path`` (JSON lines); ``path`` None keeps them in memory only.

    Reading (``records``, ``last``) takes no lock. Writing (``open_writer``, ``append``) holds the
    file's lock until ``close`` (or the object's end); ``warnings`` collects what the caller
    should log (damaged lines, removed temp files, a refused record)."""

    def __init__(self, path: str | os.PathLike | None):
        self.path = Path(path) if path else None
        self.skipped: list[str] = []          # "line N: why", from the last read
        self.warnings: list[str] = []
        self._memory: list[dict] = []
        self._fd: int | None = None
        self._owner_pid: int | None = None
        self._last_revision = 0

    # ------------------------------------------------------------------ reading
    def _scan(self, data: bytes) -> tuple[list[dict], list[tuple[int, int, bytes, str]], str]:
        """Records, damaged lines (line number, byte offset, bytes, why) and the state of the last
        line: "" (ends with "\\n"), "torn" (damaged, no end of line) or "unterminated" (a record)."""
        recs, bad = [], []
        pieces = data.split(b"\n")
        tail = pieces.pop()                  # b"" when the file ends with "\n"
        offset = 0
        for i, raw in enumerate(pieces):
            if raw.strip():
                rec, why = parse_record(raw)
                if rec is None:
                    bad.append((i + 1, offset, raw, why))
                else:
                    recs.append(rec)
            offset += len(raw) + 1
        state = ""
        if tail.strip():
            rec, why = parse_record(tail)
            if rec is None:
                bad.append((len(pieces) + 1, offset, tail, f"torn last line, no end of line ({why})"))
                state = "torn"
            else:
                recs.append(rec)
                state = "unterminated"
        return recs, bad, state

    def _read_bytes(self) -> bytes | None:
        try:
            with open(self.path, "rb") as f:
                return f.read()
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise UserError(f"{self.path}: cannot read parameter history ({exc.strerror})") from None

    def records(self) -> list[dict]:
        """The valid records in file order; damaged lines are listed in ``skipped`` and summed up
        in one line of ``warnings``."""
        self.skipped = []
        if self.path is None:
            return list(self._memory)
        data = self._read_bytes()
        if data is None:
            return []
        recs, bad, _tail = self._scan(data)
        self.skipped = [f"line {n}: {why}" for n, _, _, why in bad]
        if bad:
            self.warnings.append(self._damage_summary(bad, "ignored"))
        return recs

    def take_warnings(self) -> list[str]:
        """The lines to log since the last call (damaged lines, removed temp files, a replaced file)."""
        out, self.warnings = self.warnings, []
        return out

    def _damage_summary(self, bad, done: str) -> str:
        listed = "; ".join(f"line {n}: {why}" for n, _, _, why in bad[:3])
        more = f"; and {len(bad) - 3} more" if len(bad) > 3 else ""
        return (f"parameter history {self.path}: {len(bad)} damaged line(s) {done} ({listed}{more}); "
                f"the writer keeps copies in {damaged_path(self.path)}")

    def last(self, line: str | None = None) -> dict | None:
        """The last record (of line ``line`` when given: records of other lines are passed over)."""
        recs = [r for r in self.records() if line is None or r.get("line") == line]
        return recs[-1] if recs else None

    # ------------------------------------------------------------------ writing
    @property
    def writing(self) -> bool:
        return self._fd is not None and self._owner_pid == os.getpid()

    def open_writer(self) -> list[str]:
        """Become the file's one writer (kept until ``close``): lock, set damaged lines aside, cut a
        torn last line, remove old temp files. Returns the lines to log (``append`` puts them in
        ``warnings`` when it opens the writer itself).
        Raises ``UserError`` when another writer holds the file or it cannot be opened."""
        if self.path is None or self.writing:
            return []
        if self._fd is not None:               # inherited over fork: the parent's lock, not ours
            os.close(self._fd)
            self._fd = None
        created = not self.path.exists()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)   # read: see _reopen
        except OSError as exc:
            raise UserError(f"{self.path}: cannot open parameter history for writing ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _holder_pid(fd)
            os.close(fd)
            who = f" (pid {pid})" if pid is not None else ""
            raise UserError(f"{self.path}: parameter history already has a writer{who}; one updater per "
                            f"history file (give this one another history_path)") from None
        except OSError as exc:
            os.close(fd)
            raise UserError(f"{self.path}: cannot lock parameter history ({exc.strerror})") from None
        self._fd, self._owner_pid = fd, os.getpid()
        try:
            if created:
                _fsync_dir(self.path.parent)
            said = self._recover()
        except OSError as exc:
            self.close()
            raise UserError(f"{self.path}: cannot recover parameter history ({exc.strerror})") from None
        except BaseException:
            self.close()
            raise
        return said

    def _recover(self) -> list[str]:
        """Under the lock: revision to continue from, damaged lines set aside, torn tail cut,
        old temp files removed."""
        said = []
        data = self._read_bytes() or b""
        recs, bad, tail = self._scan(data)
        self._last_revision = max([self._last_revision] + [int(r["revision"]) for r in recs])
        kept_aside = True
        if bad:
            try:
                self._set_aside(bad)
                said.append(self._damage_summary(bad, "skipped"))
            except OSError as exc:
                kept_aside = False
                said.append(f"parameter history {self.path}: {len(bad)} damaged line(s) skipped, but they cannot be "
                            f"copied to {damaged_path(self.path)} ({exc.strerror}): they stay in the history")
        if tail == "torn" and kept_aside:     # cut it (its copy is set aside): the next record starts its own line
            os.ftruncate(self._fd, bad[-1][1])
            os.fsync(self._fd)
        elif tail:                            # end the line: a record, or a tear we could not copy
            self._write_line(b"\n")
        removed, n_bytes = [], 0
        pat = re.compile(re.escape(self.path.name) + r"\.[A-Za-z0-9_]{8}\.tmp")
        for p in self.path.parent.iterdir():
            if pat.fullmatch(p.name):
                try:
                    size = p.stat().st_size
                    p.unlink()
                    removed.append(p.name)
                    n_bytes += size
                except FileNotFoundError:
                    pass
                except OSError as exc:          # not ours to fail on: say so and write on
                    said.append(f"parameter history {self.path}: cannot remove the old temp file {p} ({exc.strerror})")
        if removed:
            said.append(f"parameter history {self.path}: removed {len(removed)} temp file(s) of an interrupted "
                        f"earlier write ({n_bytes} bytes)")
        return said

    def _set_aside(self, bad) -> None:
        """Append damaged lines not already there to the damaged file (fsync'ed)."""
        dpath = damaged_path(self.path)
        seen = set()
        if dpath.exists():
            for raw in dpath.read_bytes().splitlines():
                try:
                    d = json.loads(raw)
                    seen.add((d.get("line"), d.get("text")))
                except ValueError:
                    continue
        rows = []
        for n, off, raw, why in bad:
            text = raw.decode("utf-8", "backslashreplace")
            if (n, text) in seen:
                continue
            cut = why.startswith("torn last line")
            rows.append(json.dumps({"schema": DAMAGED_SCHEMA, "history": self.path.name, "line": n,
                                    "offset_bytes": off, "reason": why, "text": text,
                                    "action": "cut off the history" if cut else "left in the history, skipped on read",
                                    "time_unix_s": time.time()}) + "\n")
        if not rows:
            return
        created = not dpath.exists()
        dfd = os.open(dpath, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(dfd, "".join(rows).encode())
            os.fsync(dfd)
        finally:
            os.close(dfd)
        if created:
            _fsync_dir(dpath.parent)

    def _write_line(self, data: bytes) -> None:
        """One os.write on the O_APPEND descriptor, then fsync; on failure the file is cut back."""
        size = os.fstat(self._fd).st_size
        try:
            n = os.write(self._fd, data)
            if n != len(data):
                raise OSError(28, f"short write ({n} of {len(data)} bytes)")
            os.fsync(self._fd)
        except OSError:
            try:
                os.ftruncate(self._fd, size)
            except OSError:
                pass
            raise

    def _same_file(self) -> bool:
        try:
            a, b = os.stat(self.path), os.fstat(self._fd)
        except OSError:
            return False
        return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)

    def _reopen(self) -> None:
        """The file was removed (written again from the open descriptor, so no record is lost) or
        replaced (continue in the new file, revisions still increasing) while we held it."""
        removed = not self.path.exists()
        if removed:
            size = os.fstat(self._fd).st_size
            data = os.pread(self._fd, size, 0) if size else b""
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                try:
                    if data:
                        os.write(fd, data)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                _fsync_dir(self.path.parent)
            except FileExistsError:             # someone else created it meanwhile: continue there
                removed = False
        self.close()
        self.warnings.append(f"parameter history {self.path}: " + (
            "removed by another program while this writer held it; written again with its records" if removed else
            "replaced by another program while this writer held it; continuing in the file now there"))

    def append(self, parameters: dict, data_used: dict | None = None, fit: dict | None = None,
               _before_write=None, line: str | None = None) -> dict:
        """Store one accepted update; returns the record (with its revision). Raises ``UserError``
        (nothing stored) for a non-finite parameter value, another writer, or a failed write."""
        for name, p in parameters.items():
            v = p.get("value") if isinstance(p, Mapping) else None
            v = v.item() if hasattr(v, "item") else v
            if not _is_finite_number(v):
                where = "memory" if self.path is None else str(self.path)
                raise UserError(f"parameter {name}: value {v!r} is not a finite number; update not stored in "
                                f"the parameter history ({where})")
        if self.path is None:
            rev = (self._memory[-1]["revision"] + 1) if self._memory else 1
        else:
            if self.writing and not self._same_file():
                self._reopen()
            self.warnings.extend(self.open_writer())
            rev = self._last_revision + 1
        rec = _finite_or_null({"schema": SCHEMA, "revision": rev, "time_unix_s": time.time(), "line": line,
                               "parameters": parameters, "data_used": data_used or {}, "fit": fit or {}})
        if self.path is None:
            self._memory.append(rec)
            return rec
        data = (json.dumps(rec, allow_nan=False) + "\n").encode()
        if _before_write is not None:           # test hook: a crash before the record is written
            _before_write()
        try:
            self._write_line(data)
        except OSError as exc:
            raise UserError(f"{self.path}: cannot append to the parameter history ({exc.strerror}); "
                            f"revision {rev} not stored") from None
        self._last_revision = rev
        return rec

    def close(self) -> None:
        """Stop writing: release the lock (readers never needed it)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)   # the flock goes with the last descriptor (a forked child's copy never releases it)

    def __enter__(self) -> "ParameterHistory":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

"""Durable store of accepted parameter updates: a JSON-lines file, one record per accepted update.

Atomic append: the whole file is rewritten to a temporary file in the same directory (previous lines
+ the new record), flushed and fsync'ed, then renamed over the history (os.replace is atomic on
POSIX) and the directory is fsync'ed. A crash or kill at any point leaves either the previous or the
new complete history, never a partial one. On load, a malformed trailing line (e.g. a file edited or
appended by another tool) is skipped with the reason recorded in ``skipped``.
Hand-written: a few lines; sqlite would also do, but JSON lines stay readable with any tool.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping

from maglev_ros.errors import UserError

SCHEMA = "maglev-param-history/1"


def line_key(metadata: Mapping[str, Any]) -> str:
    """Identity of a test line for the history: a hash of the metadata's ``line`` and ``design``
    blocks (the contract has no line id; parameters updated on one line never apply to another)."""
    ident = {"line": metadata.get("line"), "design": metadata.get("design")}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]


class ParameterHistory:
    """Accepted updates in ``path`` (JSON lines); ``path`` None keeps them in memory only."""

    def __init__(self, path: str | os.PathLike | None):
        self.path = Path(path) if path else None
        self.skipped: list[str] = []
        self._memory: list[dict] = []

    def records(self) -> list[dict]:
        self.skipped = []
        if self.path is None:
            return list(self._memory)
        if not self.path.exists():
            return []
        out = []
        try:
            text = self.path.read_text()
        except OSError as exc:
            raise UserError(f"{self.path}: cannot read parameter history ({exc})") from None
        for i, line in enumerate(text.splitlines()):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict) or rec.get("schema") != SCHEMA:
                    raise ValueError("not a history record")
                out.append(rec)
            except ValueError as exc:
                self.skipped.append(f"line {i + 1}: {exc}")
        return out

    def last(self, line: str | None = None) -> dict | None:
        """The last record (of line ``line`` when given: records of other lines are passed over)."""
        recs = [r for r in self.records() if line is None or r.get("line") == line]
        return recs[-1] if recs else None

    def append(self, parameters: dict, data_used: dict | None = None, fit: dict | None = None,
               _before_rename=None, line: str | None = None) -> dict:
        """Store one accepted update; returns the record (with its revision)."""
        prev = self.records()
        rec = {"schema": SCHEMA, "revision": (prev[-1]["revision"] + 1) if prev else 1,
               "time_unix_s": time.time(), "line": line, "parameters": parameters,
               "data_used": data_used or {}, "fit": fit or {}}
        if self.path is None:
            self._memory.append(rec)
            return rec
        body = "".join(json.dumps(r, allow_nan=False) + "\n" for r in prev + [rec])
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(body)
                f.flush()
                os.fsync(f.fileno())
            if _before_rename is not None:      # test hook: simulate a crash between write and rename
                _before_rename()
            os.replace(tmp, self.path)
            dfd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return rec

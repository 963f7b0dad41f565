"""Progress of long work (stage, count, elapsed time, ETA) for a person watching a command.

The science core reports through a :class:`Progress` and never imports a UI library:
``progress.stage(name, total=None)`` when a named stage starts (``total``: the count of steps it
will take, when known), ``progress.advance(n=1, note="")`` per finished step (a hypothesis, a
simulation, a sample), ``progress.note(text)`` for a one-off message (what ``log=`` callbacks
print) and ``progress.done()`` at the end; ``progress.steps(items)`` yields the items and
advances after each. The default :data:`NULL` does nothing.

The commands pick a renderer with :func:`for_cli`: nothing with ``--quiet``; a tqdm bar with the
stage, count and ETA when stderr is a terminal; otherwise plain lines, throttled to one per
``min_interval_s`` for counts, and a line after ``heartbeat_s`` without one, so a log shows the
work is alive during a long single step. Everything goes to stderr: stdout stays the result.
A renderer started while another is active (the demo running ``update``) nests under it.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from typing import Callable, Iterable, Iterator, TextIO, TypeVar

T = TypeVar("T")

__all__ = ["Progress", "NULL", "PlainProgress", "BarProgress", "RecordingProgress", "for_cli", "format_s"]


class Progress:
    """The protocol, and the no-op default the core functions take."""

    def stage(self, name: str, total: int | None = None) -> None:
        pass

    def advance(self, n: int = 1, note: str = "") -> None:
        pass

    def note(self, text: str) -> None:
        pass

    def done(self) -> None:
        pass

    def steps(self, items: Iterable[T], note: Callable[[T], str] | None = None) -> Iterator[T]:
        """Yield ``items``, one :meth:`advance` after each is dealt with (use in a loop or comprehension)."""
        for item in items:
            yield item
            self.advance(1, note(item) if note is not None else "")

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.done()


NULL = Progress()


def format_s(seconds: float) -> str:
    """``42s``, ``3m05s``, ``1h02m``: short enough for a progress line."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


class RecordingProgress(Progress):
    """Keeps every call (for tests): ``events`` is a list of (kind, name-or-note, count)."""

    def __init__(self) -> None:
        self.events: list[tuple[str, str, int | None]] = []
        self.stages: list[tuple[str, int | None]] = []
        self.advances: dict[str, int] = {}
        self.closed = False

    def stage(self, name: str, total: int | None = None) -> None:
        self.stages.append((name, total))
        self.advances.setdefault(name, 0)
        self.events.append(("stage", name, total))

    def advance(self, n: int = 1, note: str = "") -> None:
        name = self.stages[-1][0] if self.stages else ""
        self.advances[name] = self.advances.get(name, 0) + int(n)
        self.events.append(("advance", note, int(n)))

    def note(self, text: str) -> None:
        self.events.append(("note", text, None))

    def done(self) -> None:
        self.closed = True


# renderers now running, innermost last: only the innermost prints heartbeats
_ACTIVE: list["_Renderer"] = []
_ACTIVE_LOCK = threading.Lock()


class _Renderer(Progress):
    """Shared state of the live renderers: stage, counts and the clock; a daemon thread ticks."""

    tick_s = 1.0

    def __init__(self, label: str, stream: TextIO | None = None, clock=time.monotonic):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.t0_s = clock()
        self.stage_name = ""
        self.stage_t0_s = self.t0_s
        self.total: int | None = None
        self.count = 0
        self.last_note = ""
        self.lock = threading.RLock()
        self.closed = False
        self.failed = False
        self.depth = 0
        with _ACTIVE_LOCK:
            self.depth = len(_ACTIVE)
            _ACTIVE.append(self)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _start_ticker(self) -> None:
        self._thread = threading.Thread(target=self._run_ticker, name=f"progress-{self.label}", daemon=True)
        self._thread.start()

    def _run_ticker(self) -> None:
        while not self._stop.wait(self.tick_s):
            try:
                self.tick()
            except Exception:        # a closed stream must never take the computation down
                return

    def tick(self) -> None:
        pass

    def innermost(self) -> bool:
        with _ACTIVE_LOCK:
            return bool(_ACTIVE) and _ACTIVE[-1] is self

    def eta_s(self, now_s: float) -> float | None:
        """Remaining time of the stage at its mean pace so far (None: total unknown or no step yet)."""
        if not self.total or self.count <= 0:
            return None
        return (now_s - self.stage_t0_s) / self.count * max(self.total - self.count, 0)

    def __exit__(self, exc_type, *exc) -> None:
        self.failed = exc_type is not None
        self.done()

    def done(self) -> None:
        with self.lock:
            if self.closed:
                return
            self.closed = True
        self._stop.set()
        with _ACTIVE_LOCK:
            if self in _ACTIVE:
                _ACTIVE.remove(self)
        self._close()

    def _close(self) -> None:
        pass


class PlainProgress(_Renderer):
    """One line per event, for logs and pipes: every stage start and note, counts at most once per
    ``min_interval_s``, and a line after ``heartbeat_s`` without any (the work is alive). Lines of
    the first ``start_delay_s`` are held back and dropped if the command fails by then, so a bad
    input still gives a one-line error."""

    def __init__(self, label: str, stream: TextIO | None = None, *, min_interval_s: float = 3.0,
                 heartbeat_s: float = 5.0, start_delay_s: float = 2.0, clock=time.monotonic, ticker: bool = True):
        super().__init__(label, stream, clock)
        self.min_interval_s = float(min_interval_s)
        self.heartbeat_s = float(heartbeat_s)
        self.start_delay_s = float(start_delay_s)
        self.last_line_s = self.t0_s
        self._held: list[str] | None = []       # None once the start delay is over
        if ticker:
            self._start_ticker()

    def _write(self, lines: list[str]) -> None:
        try:
            self.stream.write("".join(ln + "\n" for ln in lines))
            self.stream.flush()
        except (OSError, ValueError):          # closed pipe or stream: progress is not worth a crash
            pass

    def _release(self, now_s: float) -> None:
        if self._held is not None and now_s - self.t0_s >= self.start_delay_s:
            held, self._held = self._held, None
            if held:
                self._write(held)

    def _emit(self, text: str, now_s: float) -> None:
        line = f"[{format_s(now_s - self.t0_s):>6s}] {self.label}: {text}"
        self.last_line_s = now_s
        self._release(now_s)
        if self._held is not None:
            self._held.append(line)
        else:
            self._write([line])

    def _count_text(self, now_s: float) -> str:
        parts = [self.stage_name]
        if self.total:
            parts.append(f"{self.count}/{self.total} ({100 * self.count / self.total:.0f} %)")
        elif self.count:
            parts.append(f"{self.count} done")
        parts.append(f"{format_s(now_s - self.stage_t0_s)} in stage")
        eta = self.eta_s(now_s)
        if eta is not None:
            parts.append(f"ETA {format_s(eta)}")
        text = ", ".join(parts[:1]) + (": " + ", ".join(parts[1:]) if len(parts) > 1 else "")
        return text + (f" - {self.last_note}" if self.last_note else "")

    def stage(self, name: str, total: int | None = None) -> None:
        with self.lock:
            now = self.clock()
            self.stage_name, self.total, self.count, self.last_note = name, total, 0, ""
            self.stage_t0_s = now
            self._emit(name + (f" (0/{total})" if total else ""), now)

    def advance(self, n: int = 1, note: str = "") -> None:
        with self.lock:
            now = self.clock()
            self.count += int(n)
            if note:
                self.last_note = note
            if now - self.last_line_s >= self.min_interval_s:
                self._emit(self._count_text(now), now)

    def note(self, text: str) -> None:
        with self.lock:
            self._emit(text, self.clock())

    def tick(self) -> None:
        with self.lock:
            if self.closed:
                return
            now = self.clock()
            self._release(now)
            if self.innermost() and now - self.last_line_s >= self.heartbeat_s:
                self._emit(self._count_text(now) + ("" if self.last_note else " - working"), now)

    def _close(self) -> None:
        with self.lock:
            if self.failed:              # on an error the command's own one-line message says it
                if self._held is not None:
                    self._held = []
                return
            self.start_delay_s = 0.0
            self._emit("done", self.clock())


class BarProgress(_Renderer):
    """A tqdm bar on a terminal: stage as its description, count/total, elapsed and ETA; notes are
    written above it. Refreshed every second so the elapsed time moves during a long step. The bar
    appears after ``start_delay_s`` (a command failing on a bad input shows only its error)."""

    _known_format = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}"
    _unknown_format = "{desc}: {n_fmt} [{elapsed}]{postfix}"

    def __init__(self, label: str, stream: TextIO | None = None, *, start_delay_s: float = 2.0,
                 clock=time.monotonic, ticker: bool = True):
        from tqdm import tqdm
        super().__init__(label, stream, clock)
        self._tqdm = tqdm
        self.start_delay_s = float(start_delay_s)
        self.bar = None
        self._held: list[str] = []        # notes before the bar appears
        self._stdout = None
        if ticker:
            self._start_ticker()

    def _show(self) -> bool:
        """Create the bar once the start delay is over; False before."""
        if self.bar is not None:
            return True
        if self.clock() - self.t0_s < self.start_delay_s:
            return False
        tqdm = self._tqdm
        for text in self._held:
            tqdm.write(text, file=self.stream)
        self._held = []
        # nested renderers (the demo's steps) take the lines below their parent and vanish when done
        self.bar = tqdm(total=self.total, initial=self.count, file=self.stream, position=self.depth,
                        leave=self.depth == 0, dynamic_ncols=True, mininterval=0.5,
                        desc=f"{self.label}: {self.stage_name}" if self.stage_name else self.label,
                        bar_format=self._known_format if self.total else self._unknown_format)
        if self.last_note:
            self.bar.set_postfix_str(self.last_note)
        # the command's own lines on the same terminal are written above the bar, not through it
        if self.depth == 0 and sys.stdout is not self.stream and _is_terminal(sys.stdout):
            self._stdout = sys.stdout
            sys.stdout = _AboveBars(sys.stdout, self.stream, tqdm)
        return True

    def stage(self, name: str, total: int | None = None) -> None:
        with self.lock:
            self.stage_name, self.total, self.count, self.last_note = name, total, 0, ""
            self.stage_t0_s = self.clock()
            if not self._show():
                return
            self.bar.bar_format = self._known_format if total else self._unknown_format
            self.bar.reset()
            self.bar.total = total         # reset(total=None) would keep the previous stage's total
            self.bar.set_description_str(f"{self.label}: {name}", refresh=False)
            self.bar.set_postfix_str("", refresh=False)
            self.bar.refresh()

    def advance(self, n: int = 1, note: str = "") -> None:
        with self.lock:
            self.count += int(n)
            if note:
                self.last_note = note
            if not self._show():
                return
            if note:
                self.bar.set_postfix_str(note, refresh=False)
            self.bar.update(int(n))

    def note(self, text: str) -> None:
        with self.lock:
            if self._show():
                self._tqdm.write(text, file=self.stream)
            else:
                self._held.append(text)

    def tick(self) -> None:
        with self.lock:
            if not self.closed and self._show():
                self.bar.refresh()

    def _close(self) -> None:
        with self.lock:
            if self.bar is not None:
                if not self.failed:          # the bar left on screen says the whole run, not its last stage
                    self.bar.bar_format = "{desc}"
                    self.bar.set_description_str(f"{self.label}: done in {format_s(self.clock() - self.t0_s)}")
                self.bar.close()
            elif not self.failed:
                for text in self._held:
                    self._tqdm.write(text, file=self.stream)
            if self._stdout is not None and isinstance(sys.stdout, _AboveBars):
                sys.stdout = sys.stdout.restore()


class _AboveBars:
    """A stdout that clears the bars on ``bar_stream`` while it writes, then redraws them."""

    def __init__(self, out: TextIO, bar_stream: TextIO, tqdm):
        self._out, self._bar_stream, self._tqdm = out, bar_stream, tqdm
        self._partial = ""          # a line is written whole: a bar redrawn after half of it would erase it

    def write(self, text: str) -> int:
        lines, _, self._partial = (self._partial + text).rpartition("\n")
        if lines or _:
            with self._tqdm.external_write_mode(file=self._bar_stream):
                self._out.write(lines + "\n")
                self._out.flush()
        return len(text)

    def flush(self) -> None:
        self._out.flush()

    def restore(self) -> TextIO:
        """The wrapped stream, after writing what is left of an unfinished line."""
        if self._partial:
            self._out.write(self._partial)
            self._partial = ""
        return self._out

    def __getattr__(self, name):
        return getattr(self._out, name)


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty() and os.environ.get("TERM", "") != "dumb"
    except (AttributeError, ValueError):
        return False


def for_cli(quiet: bool, label: str, stream: TextIO | None = None, **options) -> Progress:
    """The renderer for a command: :data:`NULL` when ``quiet``, a bar when ``stream`` (default stderr)
    is a terminal, throttled plain lines otherwise (``options``: the renderer's keyword arguments)."""
    if quiet:
        return NULL
    stream = stream if stream is not None else sys.stderr
    if _is_terminal(stream):
        try:
            return BarProgress(label, stream, **{k: v for k, v in options.items() if k == "start_delay_s"})
        except ImportError:          # tqdm missing (a colcon install without it): plain lines
            pass
    return PlainProgress(label, stream, **options)

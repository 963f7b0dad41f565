"""The recordings of a batch: a manifest (CSV or YAML) or a glob, turned into :class:`Job`\\ s.

Manifest columns (CSV header, or keys of YAML mappings; only ``bag`` is required):
``bag`` the recording; ``name`` its output directory (default: the bag's name); ``ambient`` the
ambient recording for ``update`` / ``diagnose``; ``args`` further arguments for the verb
(shell-quoted text, or a YAML list); ``time`` the recording's time (unix seconds or ISO 8601,
UTC when no zone is given; default: its first header stamp). Relative paths are taken from the
manifest's directory. YAML: a list of rows (a row may be just the bag path), or a mapping with
``recordings:`` holding that list.

With ``--glob``, every match that is a recording (a .mcap/.db3 file or a rosbag2 directory) is
one; for verbs that take a pass (``irregularity``, ``update``, ``diagnose``) the passes are the
jobs, and each pass is paired with the ambient recording among the matches that was recorded
last at or before it (else the first after it), unless ``--ambient`` names one for all.
"""
from __future__ import annotations

import csv
import glob as globmod
import hashlib
import re
import shlex
from datetime import datetime, timezone
from pathlib import Path

from maglev_ros.batch.jobs import VERBS, Job, check_args, recording_facts
from maglev_ros.errors import UserError

COLUMNS = ("bag", "name", "ambient", "args", "time")


def is_recording(p: Path) -> bool:
    """A path the bag reader opens: a .mcap/.db3 file or a rosbag2 directory."""
    if p.is_file():
        return p.suffix in (".mcap", ".db3")
    return p.is_dir() and ((p / "metadata.yaml").is_file() or len(list(p.glob("*.mcap"))) == 1)


def default_name(bag: str) -> str:
    p = Path(bag)
    stem = p.stem if p.suffix in (".mcap", ".db3", ".bag") else p.name
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", stem).lstrip(".") or "recording"
    return name


def _unique_names(names: list[str], bags: list[str]) -> list[str]:
    """Names made unique: a name shared by several bags gets a short hash of each bag's path."""
    seen: dict[str, int] = {}
    for n in names:
        seen[n] = seen.get(n, 0) + 1
    return [n if seen[n] == 1 else f"{n}-{hashlib.sha1(b.encode()).hexdigest()[:6]}"
            for n, b in zip(names, bags)]


def parse_time(value, where: str) -> float | None:
    """Unix seconds from a number or an ISO 8601 text (UTC unless it says otherwise)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if isinstance(value, datetime):
        t = value
    else:
        try:
            return float(value)
        except (TypeError, ValueError):
            pass
        try:
            t = datetime.fromisoformat(str(value).strip().replace("Z", "+00:00"))
        except ValueError:
            raise UserError(f"{where}: time {value!r}: expected unix seconds or an ISO 8601 date "
                            "and time") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.timestamp()


def _rows_csv(path: Path) -> list[tuple[str, dict]]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the manifest ({exc})") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise UserError(f"{path}: empty manifest; expected a header line with a 'bag' column")
    reader = csv.DictReader([ln for _, ln in lines])
    header = [h.strip() for h in reader.fieldnames or []]
    unknown = [h for h in header if h not in COLUMNS]
    if "bag" not in header or unknown:
        raise UserError(f"{path}: line {lines[0][0]}: "
                        + (f"unknown column {unknown[0]!r}" if unknown else "no 'bag' column")
                        + f"; expected columns {', '.join(COLUMNS)} (bag required)")
    rows = []
    for (lineno, _), rec in zip(lines[1:], reader):
        if None in rec:
            raise UserError(f"{path}: line {lineno}: more fields than the header's {len(header)}")
        rows.append((f"{path}: line {lineno}", {k.strip(): (v.strip() if isinstance(v, str) else v)
                                                for k, v in rec.items()}))
    return rows


def _rows_yaml(path: Path) -> list[tuple[str, dict]]:
    import yaml
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the manifest ({exc})") from None
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if isinstance(doc, dict) and "recordings" in doc:
        doc = doc["recordings"]
    if not isinstance(doc, list):
        raise UserError(f"{path}: expected a list of recordings (or a mapping with 'recordings:')")
    rows = []
    for i, item in enumerate(doc):
        where = f"{path}: recording {i + 1}"
        if isinstance(item, str):
            item = {"bag": item}
        if not isinstance(item, dict):
            raise UserError(f"{where}: expected a bag path or a mapping with key 'bag'")
        unknown = [k for k in item if k not in COLUMNS]
        if unknown or "bag" not in item:
            raise UserError(f"{where}: " + (f"unknown key {unknown[0]!r}" if unknown else "no key 'bag'")
                            + f"; expected keys {', '.join(COLUMNS)} (bag required)")
        rows.append((where, item))
    return rows


def _resolve(base: Path, value, where: str, key: str) -> str | None:
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    p = Path(str(value)).expanduser()
    p = (base / p) if not p.is_absolute() else p
    if not p.exists():
        raise UserError(f"{where}: {key} {value}: no such recording ({p} does not exist)")
    return str(p.resolve())


def jobs_from_manifest(path, verb: str, ambient: str | None = None) -> list[Job]:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"--manifest {path}: no such file")
    if path.suffix.lower() in (".yaml", ".yml"):
        rows = _rows_yaml(path)
    elif path.suffix.lower() == ".csv":
        rows = _rows_csv(path)
    else:
        raise UserError(f"--manifest {path}: expected a .csv, .yaml or .yml file")
    if not rows:
        raise UserError(f"{path}: no recordings listed")
    base = path.parent
    spec = VERBS[verb]
    default_amb = str(Path(ambient).resolve()) if ambient else None
    jobs, names = [], []
    for where, row in rows:
        bag = _resolve(base, row.get("bag"), where, "bag")
        if bag is None:
            raise UserError(f"{where}: bag: expected a recording path, got nothing")
        amb = _resolve(base, row.get("ambient"), where, "ambient") or default_amb
        if spec.ambient == "no" and amb is not None and row.get("ambient"):
            raise UserError(f"{where}: ambient: {verb} takes no ambient recording")
        if spec.ambient == "required" and amb is None:
            raise UserError(f"{where}: ambient: {verb} needs the ambient recording (column 'ambient' "
                            "or --ambient)")
        raw = row.get("args") or ()
        args = shlex.split(raw) if isinstance(raw, str) else [str(a) for a in raw]
        args = check_args(verb, args, where)
        name = row.get("name")
        if name is not None and str(name).strip():
            name = str(name).strip()
            if not re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9._-]*", name):
                raise UserError(f"{where}: name {name!r}: expected letters, digits, '.', '_', '-' "
                                "(not starting with '.')")
        names.append(name)
        jobs.append(Job("", verb, bag, amb if spec.ambient != "no" else None, args,
                        parse_time(row.get("time"), where), where))
    auto = _unique_names([default_name(j.bag) for j in jobs], [j.bag for j in jobs])
    final = [n if n else a for n, a in zip(names, auto)]
    dup = {n for n in final if final.count(n) > 1}
    if dup:
        first = next(j for j, n in zip(jobs, final) if n in dup)
        raise UserError(f"{first.row}: name {sorted(dup)[0]!r} is used by more than one recording")
    return [Job(n, j.verb, j.bag, j.ambient, j.args, j.time_unix_s, j.row) for n, j in zip(final, jobs)]


def jobs_from_glob(pattern: str, verb: str, ambient: str | None = None, progress=None) -> list[Job]:
    spec = VERBS[verb]
    found = sorted({str(Path(p).resolve()) for p in globmod.glob(str(Path(pattern).expanduser()), recursive=True)
                    if is_recording(Path(p))})
    if not found:
        raise UserError(f"--glob {pattern}: matches no recording (.mcap/.db3 file or rosbag2 directory)")
    where = f"--glob {pattern}"
    fixed_amb = str(Path(ambient).resolve()) if ambient else None
    if fixed_amb and not Path(fixed_amb).exists():
        raise UserError(f"--ambient {ambient}: no such recording")
    if spec.runs_on == ("pass", "ambient") and spec.ambient == "no":
        bags, pairs = found, {b: None for b in found}
    else:
        facts = {}
        if progress is not None:
            progress.stage("reading the recordings' kinds and times", total=len(found))
        for b in found:
            facts[b] = recording_facts(b)
            if progress is not None:
                progress.advance(note=Path(b).name)
        # a recording whose kind cannot be read stays a job: the verb's run says what is wrong
        bags = [b for b in found if facts[b][0] in spec.runs_on or facts[b][0] is None]
        ambients = sorted((t, b) for b, (k, t) in facts.items() if k == "ambient" and t is not None)
        pairs = {}
        for b in bags:
            if spec.ambient == "no":
                pairs[b] = None
            elif fixed_amb:
                pairs[b] = fixed_amb
            else:
                pairs[b] = pair_ambient(facts[b][1], ambients)
            if spec.ambient == "required" and pairs[b] is None:
                raise UserError(f"{where}: {b}: no ambient recording among the matches to pair it with "
                                f"({verb} needs one; give --ambient or a manifest)")
        if not bags:
            raise UserError(f"{where}: none of the {len(found)} recording(s) is a "
                            f"{' or '.join(spec.runs_on)} recording ({verb} runs on those)")
    names = _unique_names([default_name(b) for b in bags], bags)
    return [Job(n, verb, b, pairs[b], (), None, where) for n, b in zip(names, bags)]


def pair_ambient(time_s: float | None, ambients: list[tuple[float, str]]) -> str | None:
    """The ambient recorded last at or before ``time_s``, else the first after it (sorted list of
    (time, bag)); None without ambients."""
    if not ambients:
        return None
    if time_s is None:
        return ambients[-1][1]
    before = [b for t, b in ambients if t <= time_s]
    return before[-1] if before else ambients[0][1]

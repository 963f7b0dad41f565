"""One recording's job of ``maglev-ros batch``: the verb's own ``run`` on a worker, its outputs
in one directory that appears whole (temp dir + rename) or not at all.

Layout of the batch output directory ``OUT``::

    OUT/<name>/job.json      a finished job: what ran (spec), recording time, metrics, trend values
    OUT/<name>/...           the verb's outputs, stdout.txt and stderr.txt (its printout)
    OUT/.work/<name>.<hex>/  a job under way (renamed to OUT/<name> when complete; left-overs of a
                             killed worker are removed by the next run)
    OUT/.failed/<name>.json  the last failure of a job (one-line error, log tail); removed on success

A job runs in-process on the worker (``command.run(args)`` with the arguments parsed by the
command's own ``add_arguments``), so its outputs are those of a direct run of the verb; stdout
and stderr are captured into the job's files. ``VERBS`` says, per verb, the arguments that put
its outputs into the job directory and what goes into the summary; a verb is added with one line.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib
import json
import os
import secrets
import shutil
import signal
import socket
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from maglev_ros import outputs
from maglev_ros.errors import UserError
from maglev_ros.parallel import keep_freed_memory

JOB_FILE = "job.json"
WORK_DIR = ".work"
FAILED_DIR = ".failed"
SCHEMA = "maglev-batch-job/1"
# test-only: a JSON file {name: "once" | "always"}; the job of that recording kills its worker
# (SIGKILL) after writing its outputs, before the rename (once: only on its first attempt)
TEST_KILL_ENV = "MAGLEV_BATCH_TEST_KILL"


@dataclass(frozen=True)
class Job:
    """What to run for one recording (absolute paths; ``args``: extra arguments for the verb)."""
    name: str
    verb: str
    bag: str
    ambient: str | None = None
    args: tuple[str, ...] = ()
    time_unix_s: float | None = None       # given in the manifest; else read from the recording
    row: str = ""                          # where the job came from (manifest row or glob), for errors

    def spec(self) -> dict:
        """What identifies the job's result: verb, arguments and the input files' size and mtime
        (a done job whose spec differs is redone)."""
        return {"verb": self.verb, "bag": self.bag, "ambient": self.ambient, "args": list(self.args),
                "inputs": {p: _fingerprint(p) for p in (self.bag, self.ambient) if p}}


def _fingerprint(path: str) -> list:
    """[[relative file, size, mtime_ns], ...] of a bag file or directory (cheap change detection)."""
    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    out = []
    for f in files:
        try:
            st = f.stat()
        except OSError:
            continue
        out.append([str(f.relative_to(p)) if p.is_dir() else f.name, st.st_size, st.st_mtime_ns])
    return out


# ------------------------------------------------------------------------------- the verbs
@dataclass(frozen=True)
class Verb:
    """How ``batch`` runs a verb: ``module`` in maglev_ros.commands; ``argv(job, dir)`` the
    arguments that read the job's recordings and write into ``dir``; ``stdout`` a file name the
    printout goes to instead of stdout.txt (info --json); ``ambient`` whether the job takes an
    ambient recording ("required", "optional", "no"); ``runs_on`` the run kinds a --glob gives it;
    ``summarise(dir)`` -> (metrics for the table, trend panels for the plot); ``outputs`` the
    arguments it sets (refused in a manifest's per-row arguments)."""
    module: str
    argv: Callable[[Job, Path], list]
    summarise: Callable[[Path], tuple]
    ambient: str = "no"
    runs_on: tuple[str, ...] = ("pass", "ambient")
    stdout: str = "stdout.txt"
    outputs: tuple[str, ...] = ()


def _load(d: Path, name: str):
    p = d / name
    return json.loads(p.read_text()) if p.is_file() else None


def _info_summary(d: Path):
    rep = _load(d, "info.json") or {}
    span = rep.get("data_span") or {}
    m = {"message_count": rep.get("message_count"), "duration_s": span.get("duration_s"),
         "contract_errors": rep.get("errors"), "contract_warnings": rep.get("warnings")}
    return m, {"duration [s]": {"kind": "values", "series": {"data span": span.get("duration_s")}}}


def _modes_summary(d: Path):
    doc = _load(d, "modes.json") or {}
    f = [m["frequency_hz"] for m in doc.get("modes", [])]
    z = [m["damping_ratio"] for m in doc.get("modes", [])]
    m = {"n_modes": len(f), "frequencies_hz": ";".join(f"{x:.6g}" for x in f),
         "damping_ratios": ";".join(f"{x:.4g}" for x in z)}
    return m, {"mode frequency [Hz]": {"kind": "values", "series": {"modes": f}}}


def _irregularity_summary(d: Path):
    doc = _load(d, "irregularity.json") or {}
    prof = doc.get("profile") or {}
    # the profile's RMS over its valid band (what the verb prints), then EN 13848's bands where covered
    m = {"rms_valid_band_m": prof.get("rms_m"), "min_wavelength_m": prof.get("min_wavelength_m"),
         "max_wavelength_m": prof.get("max_wavelength_m")}
    series = {"valid band": None if prof.get("rms_m") is None else prof["rms_m"] * 1e3}
    for b in doc.get("band_rms", []):
        m[f"rms_{b['band']}_m"] = b.get("rms_m") if b.get("available") else None
        if b.get("available"):
            series[f"EN 13848 {b['band']}"] = b["rms_m"] * 1e3
    return m, {"irregularity RMS [mm]": {"kind": "values", "series": series}}


def _update_summary(d: Path):
    doc = _load(d, "params.json") or {}
    m, values = {}, {}
    for n, v in (doc.get("parameters") or {}).items():
        m[n] = v.get("value")
        m[f"{n}_std"] = v.get("std")
        values[n] = v.get("value")
    e = doc.get("magnet_accel_nrmse") or {}
    m["magnet_accel_nrmse_updated"] = e.get("updated")
    fu = (doc.get("frequencies_hz") or {}).get("updated") or []
    m["updated_frequencies_hz"] = ";".join(f"{x:.6g}" for x in fu)
    # one axis for parameters of every unit: each relative to its value on the earliest recording
    return m, {"updated parameter / earliest": {"kind": "values", "relative": True, "series": values}}


def _diagnose_summary(d: Path):
    doc = _load(d, "report.json") or {}
    found = [p.get("effect") for p in doc.get("missing_physics", [])]
    m = {"fit_before_nrmse": (doc.get("fit_before") or {}).get("nrmse"),
         "fit_after_nrmse": (doc.get("fit_after") or {}).get("nrmse"),
         "mismatches": len(doc.get("mismatches", [])),
         "missing_physics": ";".join(found)}
    return m, {"fit NRMSE": {"kind": "values", "series": {"before": m["fit_before_nrmse"],
                                                          "after": m["fit_after_nrmse"]}},
               "found physics": {"kind": "events", "series": {f: 1.0 for f in found}}}


def _no_summary(d: Path):
    """A verb with no figures for the table (its outputs are still linked)."""
    return {}, {}


def _with_ambient(j: Job) -> list:
    return ["--ambient", j.ambient] if j.ambient else []


VERBS: dict[str, Verb] = {
    "info": Verb("info", lambda j, d: [j.bag, "--json"], _info_summary, stdout="info.json",
                 outputs=("--json",)),
    "modes": Verb("modes", lambda j, d: [j.bag, "--json", str(d / "modes.json"), "--plot", str(d / "modes.png")],
                  _modes_summary, outputs=("--json", "--plot")),
    "irregularity": Verb("irregularity", lambda j, d: [j.bag, "--out", str(d / "irregularity.csv"), "--json",
                                                       str(d / "irregularity.json"), "--plot", str(d / "irregularity.png")],
                         _irregularity_summary, runs_on=("pass",), outputs=("--out", "--json", "--plot")),
    "update": Verb("update", lambda j, d: [*_with_ambient(j), "--pass", j.bag, "--out", str(d / "params.json"),
                                           "--plot", str(d / "plots")],
                   _update_summary, ambient="required", runs_on=("pass",),
                   outputs=("--ambient", "--pass", "--out", "--plot")),
    "diagnose": Verb("diagnose", lambda j, d: [*_with_ambient(j), "--pass", j.bag, "--out", str(d)],
                     _diagnose_summary, ambient="optional", runs_on=("pass",),
                     outputs=("--ambient", "--pass", "--out")),
}


# ------------------------------------------------------------------------------ arguments
class _Parser(argparse.ArgumentParser):
    """The command's own parser, with a mistake raised as a UserError instead of an exit."""

    def error(self, message):
        raise UserError(message)


def verb_parser(verb: str) -> argparse.ArgumentParser:
    mod = importlib.import_module(f"maglev_ros.commands.{VERBS[verb].module}")
    p = _Parser(prog=f"maglev-ros {mod.NAME}", add_help=False)
    mod.add_arguments(p)
    return p


def verb_argv(job: Job, out_dir: Path) -> list[str]:
    return [str(a) for a in VERBS[job.verb].argv(job, Path(out_dir))] + list(job.args)


def check_args(verb: str, args, where: str) -> tuple[str, ...]:
    """The per-row arguments, checked by the verb's own parser (one line naming ``where``)."""
    args = tuple(str(a) for a in args)
    taken = [a for a in args if a.split("=", 1)[0] in VERBS[verb].outputs]
    if taken:
        raise UserError(f"{where}: argument {taken[0]} is set by batch (outputs and recordings "
                        f"come from the manifest); expected other {verb} arguments")
    probe = Job("probe", verb, "BAG", "AMBIENT" if VERBS[verb].ambient != "no" else None, args)
    try:
        verb_parser(verb).parse_args(verb_argv(probe, Path("OUT")))
    except UserError as exc:
        raise UserError(f"{where}: {verb} arguments {' '.join(args)!r}: {exc}") from None
    return args


# -------------------------------------------------------------------------------- records
@dataclass
class JobResult:
    """What a job gives back (also the content of ``job.json`` and ``.failed/<name>.json``)."""
    name: str
    verb: str
    bag: str
    status: str                      # done | failed | skipped (done on an earlier run)
    error: str = ""                  # one line, for a failure
    ambient: str | None = None
    run_kind: str | None = None
    time_unix_s: float | None = None
    time_source: str = ""            # manifest | first header stamp
    elapsed_s: float | None = None
    worker: str = ""
    argv: list = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    trend: dict = field(default_factory=dict)
    files: list = field(default_factory=list)    # outputs, relative to the job directory
    log_tail: str = ""
    blas_threads: list = field(default_factory=list)   # [library, threads] seen after the job
    spec: dict = field(default_factory=dict)
    schema: str = SCHEMA

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "JobResult":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


def read_done(out: Path, job: Job) -> JobResult | None:
    """The finished result of ``job`` in ``out`` when its spec is the job's; else None."""
    d = Path(out) / job.name / JOB_FILE
    try:
        res = JobResult.from_dict(json.loads(d.read_text()))
    except (OSError, ValueError, TypeError):
        return None
    if res.status != "done" or res.spec != _jsonable(job.spec()):
        return None
    return res


def read_failed(out: Path, name: str) -> JobResult | None:
    try:
        return JobResult.from_dict(json.loads((Path(out) / FAILED_DIR / f"{name}.json").read_text()))
    except (OSError, ValueError, TypeError):
        return None


def _jsonable(d):
    return json.loads(json.dumps(d))


def recording_facts(bag: str) -> tuple[str | None, float | None]:
    """(run.kind, earliest header stamp [s]) of a recording; None where it cannot be read."""
    from maglev_ros.bag_reader import BagReader
    try:
        with BagReader(bag, strict=False) as r:
            kind = r.metadata.run_kind if r.metadata is not None else None
            return kind, r.start_time_s
    except Exception:       # an unreadable bag: the verb's own run says why
        return None, None


# ------------------------------------------------------------------------------ the worker
def _limit_threads() -> None:
    """BLAS/OpenMP at one thread in this worker (processes give the parallelism; libraries loaded
    later start from the nanny's OMP_NUM_THREADS=1 environment)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(1)


def _threads_seen() -> list:
    """[[library, threads], ...] after the job: threadpoolctl's pools, and torch's when loaded."""
    seen = set()
    try:
        from threadpoolctl import threadpool_info
        seen = {(i.get("internal_api", "?"), i.get("num_threads")) for i in threadpool_info()}
    except ImportError:
        pass
    if "torch" in sys.modules:
        seen.add(("torch", sys.modules["torch"].get_num_threads()))
    return [list(x) for x in sorted(seen)]


def _test_kill(out: Path, name: str) -> None:
    spec = os.environ.get(TEST_KILL_ENV)
    if not spec:
        return
    how = json.loads(Path(spec).read_text()).get(name)
    if how is None:
        return
    marker = Path(spec).with_name(f"{Path(spec).name}.{name}.killed")
    if how == "once" and marker.exists():
        return
    marker.touch()
    os.kill(os.getpid(), signal.SIGKILL)


def run_job(job: Job, out: str) -> JobResult:
    """Run ``job`` on this process (a Dask worker): the verb in a fresh ``OUT/.work`` directory,
    renamed to ``OUT/<name>`` when complete. Never raises for a failure of the verb: a failed
    JobResult carries its one-line error (the caller records it)."""
    out = Path(out)
    done = read_done(out, job)
    if done is not None:        # a retry after its worker died between the rename and the reply
        return done
    t0 = time.perf_counter()
    res = JobResult(job.name, job.verb, job.bag, "failed", ambient=job.ambient,
                    worker=f"{socket.gethostname()}:{os.getpid()}", spec=_jsonable(job.spec()))
    _limit_threads()
    keep_freed_memory()          # a worker of someone else's `dask worker` starts with Dask's trim threshold
    verb = VERBS[job.verb]
    work = out / WORK_DIR / f"{job.name}.{secrets.token_hex(4)}"
    work.mkdir(parents=True)
    try:
        argv = verb_argv(job, work)
        res.argv = verb_argv(job, out / job.name)        # as it reads once in place
        out_path, err_path = work / verb.stdout, work / "stderr.txt"
        with open(out_path, "w") as fo, open(err_path, "w") as fe, \
                contextlib.redirect_stdout(fo), contextlib.redirect_stderr(fe):
            try:
                args = verb_parser(job.verb).parse_args(argv)
                mod = importlib.import_module(f"maglev_ros.commands.{verb.module}")
                code = int(mod.run(args) or 0)
                res.error = "" if code == 0 else f"exit status {code}"
            except UserError as exc:
                res.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                print(f"maglev-ros {job.verb}: error: {exc}", file=sys.stderr)
            except Exception as exc:       # a bug in the verb: its traceback goes to the log
                res.error = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": ")
                traceback.print_exc()
        res.blas_threads = _threads_seen()
        res.run_kind, stamp = recording_facts(job.bag)
        res.time_unix_s, res.time_source = ((job.time_unix_s, "manifest") if job.time_unix_s is not None
                                            else (stamp, "first header stamp") if stamp is not None else (None, ""))
        res.elapsed_s = time.perf_counter() - t0
        if res.error:
            res.log_tail = "".join(err_path.read_text(errors="replace").splitlines(True)[-20:])
            return res
        res.metrics, res.trend = verb.summarise(work)
        res.status = "done"
        res.files = sorted(str(p.relative_to(work)) for p in work.rglob("*") if p.is_file()) + [JOB_FILE]
        outputs.write_json(work / JOB_FILE, res.to_dict(), indent=1, default=str)
        _test_kill(out, job.name)
        return _publish(work, out / job.name, res)
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)


def _publish(work: Path, final: Path, res: JobResult) -> JobResult:
    """Rename the complete job directory into place: exactly one directory per recording. An
    earlier result with another spec is moved aside first and removed after; one that appeared
    meanwhile (the same job run twice by the cluster) stays and this copy is dropped."""
    old = None
    if final.exists():
        try:
            prev = json.loads((final / JOB_FILE).read_text())
        except (OSError, ValueError):
            prev = {}
        if prev.get("status") == "done" and prev.get("spec") == res.spec:
            return JobResult.from_dict(prev)           # another attempt finished first
        old = work.parent / f"{final.name}.{secrets.token_hex(4)}.old"
        os.rename(final, old)
    try:
        os.rename(work, final)
    except OSError:
        if (final / JOB_FILE).is_file():               # lost a race with another attempt
            return JobResult.from_dict(json.loads((final / JOB_FILE).read_text()))
        raise
    outputs.fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    failed = final.parent / FAILED_DIR / f"{final.name}.json"
    with contextlib.suppress(OSError):
        failed.unlink()
    return res


def job_key(job: Job, run_token: str) -> str:
    """A Dask key unique to the job, its spec and this run (a cluster may keep old keys)."""
    h = hashlib.sha1(json.dumps(job.spec(), sort_keys=True).encode()).hexdigest()[:8]
    return f"maglev-batch-{job.verb}-{job.name}-{h}-{run_token}"

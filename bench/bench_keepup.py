"""Does the monitor graph keep up with a replay? Lag and output delay of each node, from outside.

Simulates a pass with the paper's sensor set (``maglev-ros simulate paper`` on a line long enough
for ``--duration`` s at 25 km/h: 10 guideway accelerations, the midspan displacement, 4 magnet
accelerations and 4 gaps at 2 kHz, position/speed at 200 Hz, 0.1 s blocks), replays it at each
``--rate`` through the whole monitor graph (``maglev_ros.launcher.launch("monitor")``) and watches
it with an observer process (bench/keepup_probe.py: DDS publish and receive times, writer sequence
numbers, header stamps, each node's ``blocks_accepted`` on /diagnostics; no node is changed).
Per node it prints:

  - out lag: stream time of the replay's newest published sample minus the newest stream stamp the
    node has published, sampled from its first output to its last (median, max; stream s),
  - in lag: the same for the newest input it has taken (its ``blocks_accepted`` mapped onto the
    messages of the topics it subscribes, in publish order; at each /diagnostics report, 1 Hz wall),
    and its backlog (messages published to it not yet taken),
  - delay: wall time from the replay publishing the sample at stream time t to the node's output
    stamped t reaching the probe (median, max),
  - warm-up (first block published -> first output), its output's stream s per wall s (x real
    time, and over the replay's achieved rate), how long after the replay's last block its last
    output came, and a verdict: keeps up / falls behind: its lag (the delay of each result that
    reaches a newer stream time, in stream s) grows with stream time: slope >= 2 % (the node runs
    at < 98 % of the stream's pace) and a growth over the second half > 3x the lag's scatter.

Who is to blame (``judge``): each node's cores at the rate (its CPU while the replay ran, per
stream second it got through, x the rate) and the machine's CPU over the same time (/proc/stat: the
other jobs' share is the machine's busy time minus this run's processes'). A node that falls
behind is blamed on itself when it needs a core or more at the rate (one executor thread cannot
have more) or when enough cores were free; on the machine when the replay alone (the peer) could not
reach the rate ("THE MACHINE CANNOT SUSTAIN ...") or when the graph needed more cores than the other
jobs left free. So the verdict means something on a loaded machine too.

Peers measured in the same run (the house style of bench/): the requested rate, the rate the
replay achieved with the graph against the replay alone with only the probe (``--no-peer`` skips
it), and each node's output rate over the replay's. The replay's reliable keep-all topics let a
slow node fall behind in its DDS queue rather than slow the replay, unless a writer's history fills
(the replay's closing line then names the topic that set the pace; printed).

    .venv/bin/python bench/bench_keepup.py [--duration 60] [--rate 1 10 30] [--json FILE]
        [--bag BAG] [--keep DIR] [--param NODE.NAME=VALUE ...] [--linger 30] [--reliable-probe]
        [--save-raw DIR] [--domain ID]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

SENSOR_BLOCK = "maglev_msgs/msg/SensorBlock"
STRING = "std_msgs/msg/String"
# a node "falls behind" when its lag grows by at least this much per stream second (it runs at
# < 98 % of the stream's pace) AND the growth is significant: the OLS slope's t statistic over its
# one-sided Student-t quantile at TREND_ALPHA (a few 1 Hz /diagnostics points with one late report
# are no trend; hundreds of results with a small steady growth are)
SLOPE_MIN = 0.02
TREND_ALPHA = 0.01
N_LAG_SAMPLES = 400
# a node that takes its last block more than this after the replay's last one did not keep up
# (twice the /diagnostics period the figure is read from)
INTAKE_LATE_S = 2.0
MIN_POINTS = 5           # results (or /diagnostics reports) in the second half needed for a trend
PROBE_START_TIMEOUT_S = 120.0


# ----------------------------------------------------------------------------- the recording
def make_recording(path: Path, duration_s: float, seed: int = 1) -> dict:
    """The paper's pass on a line long enough for ``duration_s``: the instrumented span sits 40 %
    into the run (lead-in), the rest is the vehicle running on over further spans (free decay of the
    instrumented span). Returns ``maglev-ros simulate``'s summary."""
    from maglev_ros.twin.simulate import load_scenario, simulate
    sc = load_scenario("paper", (), seed)
    speed = float(sc.raw["speed_mps"])
    span_m = float(sc.raw["line"]["span_length_m"])
    offs = np.asarray(sc.truth_config().vehicle.magnet_offsets_m, float)
    traverse_s = (span_m + offs.max() - offs.min()) / speed
    lead_s = 0.4 * duration_s
    decay_s = duration_s - lead_s - traverse_s
    if decay_s < 1.0:
        raise SystemExit(f"--duration {duration_s:g}: at least {lead_s + traverse_s + 1:.0f} s for a pass")
    k = math.ceil((offs.max() + lead_s * speed + 5.0) / span_m)       # index of the instrumented span
    x_end = k * span_m - offs.max() - lead_s * speed + duration_s * speed
    n_spans = math.ceil((x_end + offs.max() + 5.0) / span_m) + 1
    sets = [f"line.n_spans={n_spans}", f"line.instrumented_span=S{k + 1}", f"lead_in_s={lead_s:.3f}",
            f"free_decay_s={decay_s:.3f}"]
    res = simulate("paper", path, sets=sets, seed=seed, overwrite=True)
    return {"bag": res.bag, "duration_s": res.duration_s, "topics": res.topics, "sets": sets}


def bag_duration_s(bag: Path) -> float:
    from maglev_ros.bag_reader import BagReader
    with BagReader(bag) as r:
        return float(r.duration_s)


def bag_topics(bag: Path) -> dict:
    """{topic: (msgtype, count)} read back by our BagReader."""
    from maglev_ros.bag_reader import BagReader
    with BagReader(bag) as r:
        return {t: (i.msgtype, int(i.count)) for t, i in r.topics.items()}


# ----------------------------------------------------------------------------- running
class _Capture:
    """File-like sink for the launcher's prefixed node output (kept; echoed with --verbose)."""

    def __init__(self, echo: bool) -> None:
        self.lines: list[str] = []
        self.echo = echo
        self._part = ""

    def write(self, text: str) -> None:
        self._part += text
        *done, self._part = self._part.split("\n")
        self.lines.extend(done)
        if self.echo:
            sys.stderr.write(text)

    def flush(self) -> None:
        pass


class CpuSampler:
    """CPU time (user + system, all threads) of this process's child processes (the graph's nodes,
    the probe), read from /proc every ``period_s`` with the time of reading (the DDS timestamps'
    clock): a node's cost in CPU seconds per stream second, which the machine's load does not change
    (written by hand: a few lines of /proc parsing; psutil is not a dependency). Each row is
    [time_ns, cpu_s, background_cpu_s]: the last is what the node's background threads used (those
    niced below its main thread, ``nodes._common.background_thread``: a diagnosis, the magnet
    layer), summed per thread between readings (a thread that ends between two readings loses its
    last interval to the total's other part)."""

    def __init__(self, period_s: float = 0.5) -> None:
        import threading
        self.period_s = period_s
        self.series: dict[str, list] = {}          # node name -> [[time_ns, cpu_s], ...]
        self._names: dict[int, str | None] = {}
        self._stop = threading.Event()
        self._tick = os.sysconf("SC_CLK_TCK")
        self._threads: dict[tuple[int, int], float] = {}   # (pid, tid) -> its cpu_s at the last reading
        self._background: dict[int, float] = {}            # pid -> background cpu_s since first seen
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _name(self, pid: int) -> str | None:
        if pid not in self._names:
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                return None
            args = [a.decode(errors="replace") for a in argv]
            name = next((a.split(":=", 1)[1] for a in args if a.startswith("__node:=")), None)
            if name is None and any(a.endswith("keepup_probe.py") for a in args):
                name = "(probe)"
            self._names[pid] = name
        return self._names[pid]

    def _machine(self, now: int) -> None:
        """The whole machine's busy and total CPU seconds (/proc/stat's first line): the other jobs'
        share is the machine's busy time minus this run's processes'."""
        try:
            f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        except (OSError, ValueError):
            return
        idle = f[3] + (f[4] if len(f) > 4 else 0)                     # idle + iowait
        total = sum(f[:8])                                           # guest time is in user already
        self.series.setdefault("(machine)", []).append([now, (total - idle) / self._tick, total / self._tick])

    def _background_of(self, pid: int, base_nice: int) -> float:
        """Cumulative CPU of ``pid``'s threads niced below its main thread (``base_nice``)."""
        first = pid not in self._background
        total = self._background.setdefault(pid, 0.0)
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            return total
        for tid in tids:
            try:
                stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
            except OSError:
                continue
            f = stat[stat.rindex(")") + 2:].split()
            cpu = (int(f[11]) + int(f[12])) / self._tick
            key = (pid, int(tid))
            # a thread first seen in a known process started since the last reading: all of it counts
            last = self._threads.get(key, cpu if first else 0.0)
            self._threads[key] = cpu
            if int(f[16]) > base_nice:
                total += cpu - last
        self._background[pid] = total
        return total

    def _run(self) -> None:
        me = os.getpid()
        while not self._stop.is_set():
            now = time.time_ns()
            self._machine(now)
            for d in os.listdir("/proc"):
                if not d.isdigit():
                    continue
                try:
                    stat = Path(f"/proc/{d}/stat").read_text()
                except OSError:
                    continue
                fields = stat[stat.rindex(")") + 2:].split()     # after "pid (comm) "
                if int(fields[1]) != me:                          # ppid
                    continue
                name = self._name(int(d))
                if name:
                    cpu = (int(fields[11]) + int(fields[12])) / self._tick     # utime + stime
                    self.series.setdefault(name, []).append([now, cpu, self._background_of(int(d), int(fields[16]))])
            self._stop.wait(self.period_s)


def ros_env(domain_id: int) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")      # as in the test suite: BLAS threads only contend on 2 cores
    return env


def start_probe(workdir: Path, env: dict, topics: dict, reliable: bool = False, namespace: str = "",
                wait: bool = True):
    """The observer process, subscribed to the bag's topics from its start. ``wait``: return once it
    spins (else the caller makes the replay wait for the node ``keepup_probe``)."""
    out, ready = workdir / "probe.json", workdir / "probe.ready"
    for p in (out, ready):
        p.unlink(missing_ok=True)
    cmd = [sys.executable, str(HERE / "keepup_probe.py"), str(out), "--ready-file", str(ready)]
    cmd += [f"--topic={t}:{namespace.rstrip('/')}{n}" for n, (t, _) in topics.items()]
    if reliable:
        cmd.append("--reliable")
    if namespace:
        cmd += ["--namespace", namespace]
    proc = subprocess.Popen(cmd, env=env)
    deadline = time.monotonic() + PROBE_START_TIMEOUT_S
    while wait and not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"the probe did not start (exit {proc.poll()})")
        time.sleep(0.1)
    return proc, out


def stop_probe(proc, out: Path) -> dict:
    proc.send_signal(2)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise RuntimeError("the probe did not stop within 60 s of SIGINT") from None
    return json.loads(out.read_text())


def run_graph(bag: Path, rate: float, workdir: Path, env: dict, topics: dict, *, nodes=None,
              params: dict | None = None, linger_s: float = 30.0, reliable_probe: bool = False,
              verbose: bool = False) -> dict:
    """Replay ``bag`` at ``rate`` through the monitor graph (or the ``nodes`` of it) under the probe.
    Returns {"probe": what the probe saw, "log": the graph's output lines, "wall_s", "code"}."""
    from maglev_ros import launch_graph
    from maglev_ros.launcher import launch
    overrides = {"replay": {"rate": float(rate), "progress": False},
                 "updater": {"history_path": str(workdir / "twin_parameters.jsonl")}}
    for node, kv in (params or {}).items():
        overrides.setdefault(node, {}).update(kv)
    name = "monitor"
    if nodes is not None:            # a subset: a temporary graph entry beside the shipped ones
        name = "bench-keepup"
        launch_graph.GRAPHS[name] = [s for s in launch_graph.GRAPHS["monitor"]
                                     if s.needs_bag or s.name in nodes]
    # the replay also waits for the probe (it subscribes the bag's topics as it starts), so the probe
    # starts alongside the graph instead of before it
    others = [s.name for s in launch_graph.GRAPHS[name] if not s.needs_bag]
    overrides["replay"].setdefault("wait_nodes", others + ["keepup_probe"])
    (workdir / "twin_parameters.jsonl").unlink(missing_ok=True)
    cap = _Capture(verbose)
    proc, out = start_probe(workdir, env, topics, reliable_probe, wait=False)
    t0 = time.monotonic()
    try:
        with CpuSampler() as cpu:
            code = launch(name, bag=str(bag), overrides=overrides, linger_s=linger_s, env=env, out=cap)
    finally:
        wall = time.monotonic() - t0
        launch_graph.GRAPHS.pop("bench-keepup", None)
        seen = stop_probe(proc, out)
    seen["cpu"] = cpu.series
    return {"probe": seen, "log": cap.lines, "wall_s": wall, "code": code}


def run_replay_alone(bag: Path, rate: float, workdir: Path, env: dict, topics: dict,
                     reliable_probe: bool = False) -> dict:
    """The peer: the same replay with the probe as its only subscriber."""
    proc, out = start_probe(workdir, env, topics, reliable_probe)
    t0 = time.monotonic()
    try:
        rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--rate", str(rate),
                              "--quiet", "--wait-subscribers", "1"], env=env, capture_output=True, text=True)
    finally:
        wall = time.monotonic() - t0
        seen = stop_probe(proc, out)
    return {"probe": seen, "log": rep.stderr.splitlines(), "wall_s": wall, "code": rep.returncode}


# ----------------------------------------------------------------------------- analysis
def _stream_stamp_of_parameters(row) -> int | None:
    """Stream time of the data an accepted update used (the TwinParameters header is wall time)."""
    try:
        used = json.loads(row[5]).get("data_used") or {}
    except (TypeError, ValueError):
        return None
    if used.get("stamp_s") is not None:
        return int(round(float(used["stamp_s"]) * 1e9))
    if used.get("t0_s") is not None:
        return int(round((float(used["t0_s"]) + float(used.get("duration_s", 0.0))) * 1e9))
    return None


def _stats(v) -> dict:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"median": None, "max": None, "n": 0}
    return {"median": float(np.median(v)), "max": float(np.max(v)), "n": int(v.size)}


def _trend(stamp_s: np.ndarray, delay_s: np.ndarray, rate: float, min_n: int,
           second_half: bool = True) -> dict | None:
    """Does the node fall further behind as the stream goes on? Its lag, as the delay (wall s) of
    each result behind the replay's publishing of the same stream time, in stream s (x the replay's
    rate), against that stream time, over the second half of the stamps it reached (the twin's
    designed lag builds up first; results after the replay's end count too, so a short replay at a
    high rate still shows the trend; only results that reach a newer stream time count). OLS slope (stream s of lag per stream s), the growth it
    predicts over that half, the scatter around the line and the slope's t statistic. None with
    fewer than ``min_n`` points.
    ``second_half`` False: every point (a node's intake has no designed lag to build up)."""
    ok = np.isfinite(stamp_s) & np.isfinite(delay_s)
    x, y = stamp_s[ok], delay_s[ok] * rate
    # only the results that reach a newer stream time: once a node has the recording's end, later
    # reports (and late results of old stamps) say nothing about its pace
    new = np.r_[True, x[1:] > np.maximum.accumulate(x)[:-1]] if x.size else x.astype(bool)
    x, y = x[new], y[new]
    if x.size < 2:
        return None
    if second_half:
        half = x >= x.min() + 0.5 * np.ptp(x)
        x, y = x[half], y[half]
    if x.size < min_n or np.ptp(x) <= 0:
        return None
    from scipy import stats
    fit = stats.linregress(x, y)                    # OLS with the slope's standard error
    slope = float(fit.slope)
    scatter = float(np.std(y - (fit.intercept + fit.slope * x)))
    growth = slope * float(np.ptp(x))
    t = slope / fit.stderr if fit.stderr > 0 else (np.inf if slope > 0 else 0.0)
    t_crit = float(stats.t.ppf(1.0 - TREND_ALPHA, x.size - 2)) if x.size > 2 else np.inf
    return {"slope": slope, "scatter_s": scatter, "growth_s": growth, "n": int(x.size), "t": float(t),
            "falls_behind": bool(slope >= SLOPE_MIN and t > t_crit)}


def _node_names(names) -> list[str]:
    """Graph node names without DDS's placeholder for a participant whose node is not known yet."""
    return sorted(n for n in names if n and n != "_NODE_NAME_UNKNOWN_")


def analyse(probe: dict, requested_rate: float, replay_log=()) -> dict:
    """Figures of one run from what the probe saw (times: DDS publish/receive, ns since the epoch).

    Wall times are seconds after the replay published its first block, stream times seconds after
    the first sample. The stream front S(w) is the newest sample the replay has published by wall
    time w (it stays at the recording's end after the replay)."""
    ns = probe.get("namespace", "")
    topics = probe["topics"]
    pubs = {t: _node_names(v) for t, v in probe.get("publishers", {}).items()}
    subs = {t: _node_names(v) for t, v in probe.get("subscribers", {}).items()}
    inputs = sorted(t for t, e in topics.items()
                    if e["type"] == SENSOR_BLOCK and t.startswith(ns + "/testline/") and e["rows"])
    if not inputs:
        raise ValueError("the probe saw no input block")
    rows = {t: np.array([r[:5] for r in topics[t]["rows"]], dtype=np.int64) for t in inputs}
    allin = np.concatenate([rows[t] for t in inputs])
    allin = allin[np.argsort(allin[:, 0], kind="stable")]
    w0 = int(allin[0, 0])                                 # wall reference: first block published
    s0 = int(allin[:, 3].min())                           # stream reference: first sample
    w_in = (allin[:, 0] - w0) * 1e-9
    front = np.maximum.accumulate((allin[:, 4] - s0) * 1e-9)
    w_end = float(w_in[-1])                               # the replay's last block published
    stream_span = float((allin[:, 3].max() - s0) * 1e-9)  # first to last block stamp
    achieved = stream_span / w_end if w_end > 0 else float("nan")

    def stream_at(w):
        i = np.searchsorted(w_in, w, side="right") - 1
        return np.where(i >= 0, front[np.maximum(i, 0)], np.nan)

    def arrival(t):
        """Wall time the replay published the sample at stream time t (nan if never)."""
        i = np.searchsorted(front, t, side="left")
        return np.where(i < front.size, w_in[np.minimum(i, front.size - 1)], np.nan)

    # a topic the probe subscribed ahead that no node of this graph published: not part of the run
    topics = {t: e for t, e in topics.items() if e["rows"] or pubs.get(t)}
    topic_rows = []
    for t in sorted(topics):
        e = topics[t]
        seq = np.array([r[2] for r in e["rows"]], dtype=np.int64)
        info = {"topic": t, "type": e["type"], "role": "input" if t.startswith(ns + "/testline/") else "output",
                "received": int(seq.size), "publishers": pubs.get(t, []), "subscribers": subs.get(t, [])}
        if seq.size:
            info["published"] = int(seq.max())       # a writer's sequence numbers start at 1
            info["lost"] = int(seq.max() - np.unique(seq).size)
        if t in rows:
            info["stamps_monotonic"] = bool(np.all(np.diff(rows[t][:, 3]) > 0))
        topic_rows.append(info)

    # outputs with a stream stamp, per publishing node (a stamp outside the stream is wall time)
    lo_ns, hi_ns = -1_000_000_000, int(allin[:, 4].max() - s0) + 1_000_000_000
    per_node: dict[str, list] = {}
    for t, e in topics.items():
        if t.startswith(ns + "/testline/") or e["type"] == STRING:
            continue                    # the streams; text (status, events, the diagnosis) has no stamp
        node = ",".join(pubs.get(t, [])) or "?"
        outs = per_node.setdefault(node, [])
        for r in e["rows"]:
            if e["type"] == STRING:
                continue
            stamp = _stream_stamp_of_parameters(r) if len(r) >= 6 else r[3]
            if stamp is not None and lo_ns <= stamp - s0 <= hi_ns:
                outs.append((r[0], r[1], stamp, t))

    diagnostics = probe.get("diagnostics", {})
    nodes = {}
    for node in sorted(set(per_node) | set(diagnostics)):
        outs = per_node.get(node, [])
        res: dict = {"outputs": len(outs), "output_topics": sorted({o[3] for o in outs})}
        out_trend = in_trend = None
        if outs:
            o = np.array([o[:3] for o in outs], dtype=np.int64)
            o = o[np.argsort(o[:, 0], kind="stable")]
            o_pub, o_recv, o_stamp = (o[:, 0] - w0) * 1e-9, (o[:, 1] - w0) * 1e-9, (o[:, 2] - s0) * 1e-9
            res["warmup_s"] = float(o_recv[0])
            res["after_end_s"] = float(o_recv.max() - w_end)
            res["delay_s"] = _stats(o_recv - arrival(o_stamp))
            newest = np.maximum.accumulate(o_stamp)
            # sampled from its first output to its last one (catching up after the end included)
            grid = np.linspace(o_pub[0], max(o_pub[-1], o_pub[0]), N_LAG_SAMPLES)
            lag = stream_at(grid) - newest[np.searchsorted(o_pub, grid, side="right") - 1]
            res["output_lag_s"] = _stats(lag)
            out_trend = _trend(o_stamp, o_pub - arrival(o_stamp), achieved, MIN_POINTS)
            if o_stamp.size >= 2 and o_recv[-1] > o_recv[0]:
                res["rate_x"] = float((newest[-1] - o_stamp[0]) / (o_recv[-1] - o_recv[0]))
        diag = diagnostics.get(node)
        mine = [t for t in topics if topics[t]["type"] == SENSOR_BLOCK and node in subs.get(t, [])
                and topics[t]["rows"]]
        if diag and mine:
            m = np.concatenate([np.array([r[:5] for r in topics[t]["rows"]], dtype=np.int64) for t in mine])
            m = m[np.argsort(m[:, 0], kind="stable")]
            m_pub = (m[:, 0] - w0) * 1e-9
            m_front = np.maximum.accumulate((m[:, 4] - s0) * 1e-9)
            d = np.array(diag, dtype=np.int64)
            d_t, accepted = (d[:, 0] - w0) * 1e-9, d[:, 1]
            published = np.searchsorted(m_pub, d_t, side="right")
            taken = np.clip(accepted, 0, m.shape[0])
            consumed = np.where(taken > 0, m_front[np.maximum(taken - 1, 0)], np.nan)
            lag_in = stream_at(d_t) - consumed
            active = (d_t >= 0) & np.isfinite(lag_in) & ((d_t <= w_end) | (published > accepted))
            res["input_topics"] = sorted(mine)
            res["input_lag_s"] = _stats(lag_in[active])
            res["backlog_msgs"] = _stats((published - accepted)[active])
            res["accepted_final"] = int(accepted[-1])
            if np.isfinite(consumed[-1]):
                res["taken_stream_s"] = float(consumed[-1])
            # when it had taken every block published to it by the replay's end (an upper bound: the
            # reports come every second of wall time, and not while its executor is blocked)
            n_by_end = int(np.searchsorted(m_pub, w_end, side="right"))
            caught = np.flatnonzero((accepted >= n_by_end) & (d_t >= w_end))
            res["last_block_taken_s"] = float(d_t[caught[0]] - w_end) if caught.size else None
            res["published_to_it"] = int(m.shape[0])
            took = (d_t >= 0) & np.isfinite(consumed)
            in_trend = _trend(consumed[took], d_t[took] - arrival(consumed[took]), achieved, MIN_POINTS,
                              second_half=False)
        cpu = probe.get("cpu", {}).get(node)
        if cpu:
            c = np.array(cpu, dtype=float)
            c_t = (c[:, 0] - w0) * 1e-9
            sel = c_t >= 0
            done_s = res.get("taken_stream_s", stream_span)     # the stream it got through
            if sel.sum() >= 2 and done_s and done_s > 0:
                # from the first block published to the last reading (imports and set-up excluded; work
                # after the replay's end included): what a stream second costs it, on any machine load
                res["cpu_s"] = float(c[sel, 1][-1] - c[sel, 1][0])
                res["cpu_per_stream_s"] = res["cpu_s"] / done_s
                res["cores_at_rate"] = res["cpu_per_stream_s"] * requested_rate
            # the stream work alone: until it had taken the recording's last block (its end's work
            # comes after that), else until the replay's end, over the stream it got through by
            # then (the whole recording, or the part taken) -> the cores it needs to keep up
            last_in = res.get("last_block_taken_s")
            if last_in is not None:
                until, got = w_end + max(last_in, 0.0), stream_span
            else:
                until, got = w_end, _stream_by(res, diag, outs, w0, s0, w_end, topics, subs, node)
            during = sel & (c_t <= until + 0.5)
            if during.sum() >= 2 and got:
                # its background threads' work (a diagnosis, the magnet layer) yields to stream work
                bg = float(c[during, 2][-1] - c[during, 2][0]) if c.shape[1] > 2 else 0.0
                res["stream_cpu_s"] = float(c[during, 1][-1] - c[during, 1][0]) - bg
                res["stream_cores_at_rate"] = res["stream_cpu_s"] / got * requested_rate
                res["background_cpu_s"] = bg
                res["background_cores"] = bg / max(float(c_t[during][-1] - c_t[during][0]), 1e-9)
        res["output_trend"], res["input_trend"] = out_trend, in_trend
        trends = [tr for tr in (out_trend, in_trend) if tr]
        late = "last_block_taken_s" in res and (res["last_block_taken_s"] is None
                                                or res["last_block_taken_s"] > INTAKE_LATE_S)
        if any(tr["falls_behind"] for tr in trends):
            res["verdict"] = "falls behind"
        elif late:
            res["verdict"] = "falls behind (intake)"
        else:
            res["verdict"] = "keeps up" if trends or "last_block_taken_s" in res else "too few figures"
        nodes[node] = res

    machine = _machine_share(probe.get("cpu", {}), w0, w_end)
    replay_line = next((ln for ln in replay_log if "published" in ln and "real time" in ln), "")
    paced = [t for t in inputs if f"subscriber of {t} set the pace" in replay_line]
    probe_latency = (allin[:, 1] - allin[:, 0]) * 1e-9
    return {"requested_rate": requested_rate, "achieved_rate": achieved, "stream_s": stream_span,
            "wall_s": w_end, "replay_line": replay_line, "paced_topics": paced,
            "paced_by": sorted({n for t in paced for n in subs.get(t, [])}),
            "probe_latency_s": _stats(probe_latency), "topics": topic_rows, "nodes": nodes, "machine": machine}


def _stream_by(res: dict, diag, outs, w0: int, s0: int, w_end: float, topics, subs, node) -> float | None:
    """Stream seconds a node had got through when the replay published its last block: the newest
    input it had taken by then (its /diagnostics), else the newest stamp it had published."""
    best = None
    if diag:
        mine = [t for t in topics if topics[t]["type"] == SENSOR_BLOCK and node in subs.get(t, []) and topics[t]["rows"]]
        if mine:
            m = np.concatenate([np.array([r[:5] for r in topics[t]["rows"]], dtype=np.int64) for t in mine])
            m = m[np.argsort(m[:, 0], kind="stable")]
            front = np.maximum.accumulate((m[:, 4] - s0) * 1e-9)
            d = np.array(diag, dtype=np.int64)
            before = d[(d[:, 0] - w0) * 1e-9 <= w_end + 0.5]
            if before.size and before[-1, 1] > 0:
                best = float(front[min(int(before[-1, 1]), front.size) - 1])
    if best is None and outs:
        o = np.array([x[:3] for x in outs], dtype=np.int64)
        o = o[(o[:, 0] - w0) * 1e-9 <= w_end + 0.5]
        if o.size:
            best = float((o[:, 2].max() - s0) * 1e-9)
    return best if best and best > 0 else None


def _machine_share(cpu: dict, w0: int, w_end: float) -> dict | None:
    """CPU of the machine while the replay ran: its cores, how many the other jobs kept busy (the
    machine's busy time minus this run's processes'), and so how many were left for this run."""
    m = cpu.get("(machine)")
    if not m or len(m) < 2:
        return None
    m = np.array(m, dtype=float)
    t = (m[:, 0] - w0) * 1e-9
    sel = (t >= 0) & (t <= w_end + 0.5)
    if sel.sum() < 2:
        sel = np.argsort(np.abs(t))[:2]            # a run shorter than two readings: the nearest two
    wall = (m[sel, 0].max() - m[sel, 0].min()) * 1e-9
    if wall <= 0:
        return None
    busy = (m[sel, 1].max() - m[sel, 1].min()) / wall
    cores = (m[sel, 2].max() - m[sel, 2].min()) / wall
    lo, hi = m[sel, 0].min(), m[sel, 0].max()
    by_process = {}
    for name, series in cpu.items():
        if name == "(machine)":
            continue
        c = np.array(series, dtype=float)
        inside = c[(c[:, 0] >= lo) & (c[:, 0] <= hi)]
        if inside.shape[0] >= 2:
            by_process[name] = float(inside[-1, 1] - inside[0, 1]) / wall
    ours = sum(by_process.values())
    others = max(busy - ours, 0.0)
    return {"cores": cores, "busy_cores": busy, "ours_cores": ours, "others_cores": others,
            "free_for_us_cores": max(cores - others, 0.0), "cores_by_process": by_process}


# a node that needs at least this many cores at the rate cannot keep up on any machine: one executor
# thread (and Python's one interpreter lock) gives it one core at most
ONE_CORE = 0.9
# the replay alone must reach this fraction of the requested rate for the machine to sustain it
PEER_MIN = 0.95


def judge(r: dict, peer: dict | None) -> None:
    """Who is to blame for a node falling behind: the node (it needs a core or more at this rate),
    or this machine at this moment (the replay alone cannot reach the rate, or the graph needs more
    cores than the other jobs left free). Sets each node's ``blame`` and the run's ``capacity``."""
    rate = r["requested_rate"]
    machine = r.get("machine") or {}
    # the nodes' stream work at the rate, plus what the replay and the probe used meanwhile
    need = sum(n.get("stream_cores_at_rate") or 0.0 for n in r["nodes"].values())
    need += sum(c for name, c in (machine.get("cores_by_process") or {}).items() if name not in r["nodes"])
    free = machine.get("free_for_us_cores")
    alone = peer["achieved_rate"] if peer else None
    r["capacity"] = {"graph_needs_cores": need, "free_cores": free, "replay_alone_rate": alone,
                     "machine_cannot_replay": alone is not None and alone < PEER_MIN * rate,
                     "graph_over_capacity": free is not None and need > free}
    for n in r["nodes"].values():
        if not n["verdict"].startswith("falls behind"):
            n["blame"] = None
            continue
        own = n.get("stream_cores_at_rate")
        if own is not None and own >= ONE_CORE:
            n["blame"] = f"the node: it needs {own:.2f} cores at {rate:g}x, one is its most"
        elif r["capacity"]["machine_cannot_replay"]:
            n["blame"] = f"the machine: the replay alone reached {alone:.2f}x of {rate:g}x"
        elif r["capacity"]["graph_over_capacity"]:
            n["blame"] = (f"the machine: the graph needs {need:.2f} cores at {rate:g}x, the other jobs left "
                          f"{free:.2f} of {machine['cores']:.0f} free")
        elif free is None or own is None:
            n["blame"] = "unknown: no CPU figures of the machine or the node"
        else:
            n["blame"] = f"the node: {own:.2f} cores needed, enough were free"


# ----------------------------------------------------------------------------- printing
def _f(x, fmt="{:.2f}", none="-"):
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def print_run(r: dict, peer: dict | None) -> None:
    rate = r["requested_rate"]
    line = (f"rate {rate:g}x: the replay achieved {_f(r['achieved_rate'])}x real time with the graph "
            f"({r['stream_s']:.1f} s of stream in {r['wall_s']:.1f} s wall; "
            f"{_f(r['achieved_rate'] / rate)} of the requested rate")
    if peer:
        line += f", {_f(r['achieved_rate'] / peer['achieved_rate'])} of the replay alone ({_f(peer['achieved_rate'])}x)"
    print(line + ")")
    if r["replay_line"]:
        print("  replay: " + r["replay_line"].split("]: ", 1)[-1])
    if r["paced_by"]:
        print(f"  the replay was held back by the reliable subscribers of {', '.join(r['paced_topics'])}: "
              f"{', '.join(r['paced_by'])}")
    lost = sum(t.get("lost", 0) for t in r["topics"])
    if lost:
        print(f"  the probe (best effort) lost {lost} of {sum(t['received'] for t in r['topics']) + lost} messages "
              "under this load: the figures are of the rest (--reliable-probe takes all, and joins the back-pressure)")
    cap, mach = r.get("capacity") or {}, r.get("machine") or {}
    if mach:
        print(f"  machine while the replay ran: {mach['cores']:.1f} cores, {mach['others_cores']:.2f} busy with "
              f"other jobs, {mach['ours_cores']:.2f} with this run; the graph's stream work needs "
              f"{_f(cap.get('graph_needs_cores'))} cores at {rate:g}x ({_f(mach['free_for_us_cores'])} were free)")
    if cap.get("machine_cannot_replay"):
        print(f"  THE MACHINE CANNOT SUSTAIN {rate:g}x NOW: the replay alone reached {cap['replay_alone_rate']:.2f}x; "
              "a node falling behind here says nothing about the node")
    elif cap.get("graph_over_capacity"):
        print("  the graph needs more cores than the other jobs left free: falling behind is this machine's "
              "load unless a node needs a core or more itself (blame below)")
    lat = r["probe_latency_s"]
    print(f"  probe latency (replay publish -> probe receive): median {_f(lat['median'] * 1e3, '{:.1f}')} ms, "
          f"max {_f(lat['max'] * 1e3, '{:.1f}')} ms")
    print(f"  {'node':13s} {'out':>5s} {'warm-up':>7s} {'out lag':>11s} {'in lag':>11s} {'last in':>7s} "
          f"{'delay':>11s} {'x real':>6s} {'/replay':>7s} {'cores':>9s} {'slope':>7s} {'after':>6s}  verdict")
    print(f"  {'':13s} {'':>5s} {'wall s':>7s} {'med/max':>11s} {'med/max':>11s} {'wall s':>7s} "
          f"{'med/max':>11s} {'time':>6s} {'':>7s} {'at rate':>9s} {'':>7s} {'end s':>6s}")
    for node, n in sorted(r["nodes"].items()):
        def mm(d, fmt="{:.1f}"):
            d = d or {}
            return _f(d.get("median"), fmt) + "/" + _f(d.get("max"), fmt)
        tr = n.get("output_trend") or n.get("input_trend") or {}
        rx = n.get("rate_x")
        last_in = n.get("last_block_taken_s", "absent")
        last_in = "-" if last_in == "absent" else "never" if last_in is None else f"{last_in:.1f}"
        print(f"  {node:13s} {n['outputs']:5d} {_f(n.get('warmup_s'), '{:.1f}'):>7s} "
              f"{mm(n.get('output_lag_s')):>11s} {mm(n.get('input_lag_s')):>11s} {last_in:>7s} "
              f"{mm(n.get('delay_s'), '{:.1f}'):>11s} "
              f"{_f(rx, '{:.1f}'):>6s} {_f(None if rx is None else rx / r['achieved_rate']):>7s} "
              f"{_f(n.get('stream_cores_at_rate'), '{:.3f}'):>9s} "
              f"{_f(tr.get('slope'), '{:+.3f}'):>7s} {_f(n.get('after_end_s'), '{:.1f}'):>6s}  {n['verdict']}"
              + (f" ({n['blame']})" if n.get("blame") else ""))
    print("  (lags in stream s: the replay's newest published sample minus the newest the node published "
          "(out) or took (in); last in: when it had taken every block, after the replay's last; delay: "
          "replay publish -> output at the probe; x real time: the node's output stream s per wall s, "
          "/replay: over the replay's achieved rate; cores at rate: its CPU while the replay ran per stream s "
          "it got through, x the rate: the cores it needs to keep up, its background threads' left out)")
    bg = {node: n["background_cores"] for node, n in sorted(r["nodes"].items()) if n.get("background_cores", 0) > 0.01}
    if bg:
        print("  background threads (niced: they yield to the stream work) used meanwhile: "
              + ", ".join(f"{node} {c:.2f} cores" for node, c in bg.items()))
    print(f"  {'topic':44s} {'role':6s} {'received':>8s} {'published':>9s} {'lost':>5s}  publisher -> subscribers")
    for t in r["topics"]:
        print(f"  {t['topic']:44s} {t['role']:6s} {t['received']:8d} {t.get('published', 0):9d} "
              f"{t.get('lost', 0):5d}  {','.join(t['publishers']) or '?'} -> {','.join(t['subscribers']) or '-'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="recording length [s] (default 60)")
    ap.add_argument("--rate", type=float, nargs="+", default=[10.0], help="replay rates (default 10)")
    ap.add_argument("--bag", help="use this recording instead of simulating one")
    ap.add_argument("--keep", help="simulate the recording into this directory and keep it")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="a node parameter for the run (YAML value)")
    ap.add_argument("--linger", type=float, default=30.0, help="graph kept running after the replay ends [s]")
    ap.add_argument("--no-peer", action="store_true", help="skip the replay-alone peer run")
    ap.add_argument("--reliable-probe", action="store_true", help="the probe subscribes reliably (back-pressure)")
    ap.add_argument("--json", help="write every figure to this JSON file")
    ap.add_argument("--domain", type=int, default=220 + os.getpid() % 12,
                    help="ROS_DOMAIN_ID of the runs (default 220-231: apart from the tests' domains)")
    ap.add_argument("--save-raw", metavar="DIR", help="keep what the probe saw and the graph's output per run")
    ap.add_argument("--verbose", action="store_true", help="echo the graph's output")
    a = ap.parse_args(argv)
    import yaml
    params: dict = {}
    for p in a.param:
        key, _, value = p.partition("=")
        node, _, name = key.partition(".")
        if not (node and name and _):
            raise SystemExit(f"--param {p}: expected NODE.NAME=VALUE")
        params.setdefault(node, {})[name] = yaml.safe_load(value)
    load = os.getloadavg()
    print(f"machine: load average {load[0]:.1f} / {load[1]:.1f} (1 / 5 min) on {os.cpu_count()} cores "
          "(shared with other jobs: figures are of this machine at this moment)")
    with tempfile.TemporaryDirectory(prefix="bench_keepup_") as tmp:
        work = Path(tmp)
        if a.bag:
            bag = Path(a.bag)
            rec = {"bag": str(bag)}
        else:
            bag = Path(a.keep or tmp) / f"paper_pass_{a.duration:g}s"
            t = time.monotonic()
            rec = make_recording(bag, a.duration, a.seed)
            print(f"recording: simulated {rec['duration_s']:.1f} s ({', '.join(rec['sets'])}) "
                  f"in {time.monotonic() - t:.0f} s -> {bag}")
        topics = bag_topics(bag)
        dur_s = bag_duration_s(bag)
        if "window_s" not in params.get("modal_id", {}) and dur_s and dur_s < 2 * 120.0:
            params.setdefault("modal_id", {})["window_s"] = float(min(120.0, dur_s / 2))
            print(f"modal_id.window_s = {params['modal_id']['window_s']:g} s for this run (the shipped 120 s "
                  "window would not fill twice in this recording; --param modal_id.window_s=... overrides)")
        print("topics: " + ", ".join(f"{t} {n}" for t, (_, n) in sorted(topics.items())))
        results = {"recording": rec, "params": params, "load_average": load, "runs": []}
        env = ros_env(a.domain)
        for rate in a.rate:
            peer = None
            if not a.no_peer:
                alone = run_replay_alone(bag, rate, work, env, topics, a.reliable_probe)
                peer = analyse(alone["probe"], rate, alone["log"])
            run = run_graph(bag, rate, work, env, topics, params=params, linger_s=a.linger,
                            reliable_probe=a.reliable_probe, verbose=a.verbose)
            if a.save_raw:
                Path(a.save_raw).mkdir(parents=True, exist_ok=True)
                Path(a.save_raw, f"graph_{rate:g}x.json").write_text(json.dumps(run))
                if not a.no_peer:
                    Path(a.save_raw, f"alone_{rate:g}x.json").write_text(json.dumps(alone))
            res = analyse(run["probe"], rate, run["log"])
            res["graph_wall_s"] = run["wall_s"]
            res["exit_code"] = run["code"]
            judge(res, peer)
            print()
            print_run(res, peer)
            results["runs"].append({"rate": rate, "graph": res, "replay_alone": peer})
        if a.json:
            Path(a.json).write_text(json.dumps(results, indent=1, default=float))
            print(f"\nwrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The batch's summary: a table with a row per recording (``summary.csv``, ``summary.parquet``),
a trend plot over the recordings' times (``trend.png``) and ``index.html`` linking each
recording's outputs; all four replaced together (:class:`maglev_ros.outputs.Batch`)."""
from __future__ import annotations

import csv
import html
import io
import math
from datetime import datetime, timezone
from pathlib import Path

from maglev_ros import outputs
from maglev_ros.batch.jobs import FAILED_DIR, JobResult

FIRST_COLUMNS = ("name", "status", "error", "recording_time_utc", "time_unix_s", "time_source",
                 "run_kind", "bag", "ambient", "ran_this_run", "elapsed_s", "worker", "output")
FILES = ("summary.csv", "summary.parquet", "trend.png", "index.html")


def _utc(t: float | None) -> str:
    return "" if t is None else datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="milliseconds")


def _order(results: list[JobResult]) -> list[JobResult]:
    """By recording time; recordings without one after, by name."""
    return sorted(results, key=lambda r: (r.time_unix_s is None, r.time_unix_s or 0.0, r.name))


def table_rows(results: list[JobResult], ran: set[str]) -> list[dict]:
    rows = []
    for r in _order(results):
        row = {"name": r.name, "status": r.status, "error": r.error,
               "recording_time_utc": _utc(r.time_unix_s), "time_unix_s": r.time_unix_s,
               "time_source": r.time_source, "run_kind": r.run_kind, "bag": r.bag, "ambient": r.ambient,
               "ran_this_run": r.name in ran, "elapsed_s": r.elapsed_s, "worker": r.worker,
               "output": r.name if r.status == "done" else f"{FAILED_DIR}/{r.name}.json"}
        for k, v in r.metrics.items():
            row.setdefault(k, v)
        rows.append(row)
    return rows


def _columns(rows: list[dict]) -> list[str]:
    cols = list(FIRST_COLUMNS)
    for row in rows:
        cols += [k for k in row if k not in cols]
    return cols


def csv_text(rows: list[dict]) -> str:
    fh = io.StringIO()
    w = csv.DictWriter(fh, fieldnames=_columns(rows), lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow({k: ("" if v is None else v) for k, v in row.items()})
    return fh.getvalue()


def parquet_bytes(rows: list[dict]) -> bytes:
    """The table as Parquet; a column's type from its values (bool, int64, float64, else string)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    cols = _columns(rows)
    arrays, fields = [], []
    for c in cols:
        vals = [row.get(c) for row in rows]
        present = [v for v in vals if v is not None]
        if present and all(isinstance(v, bool) for v in present):
            typ = pa.bool_()
        elif present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
            typ = pa.int64()
        elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            typ, vals = pa.float64(), [None if v is None else float(v) for v in vals]
        else:
            typ, vals = pa.string(), [None if v is None else str(v) for v in vals]
        arrays.append(pa.array(vals, type=typ))
        fields.append(pa.field(c, typ))
    buf = io.BytesIO()
    pq.write_table(pa.Table.from_arrays(arrays, schema=pa.schema(fields)), buf)
    return buf.getvalue()


def trend_figure(results: list[JobResult], title: str):
    """One panel per trend quantity over the recordings' times (done recordings with a time)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    done = [r for r in _order(results) if r.status == "done" and r.time_unix_s is not None]
    panels: dict[str, dict] = {}
    for r in done:
        for p, spec in r.trend.items():
            panels.setdefault(p, {"kind": spec.get("kind", "values"), "relative": spec.get("relative", False),
                                  "series": {}})
            for label, v in (spec.get("series") or {}).items():
                panels[p]["series"].setdefault(label, []).append(
                    (datetime.fromtimestamp(r.time_unix_s, timezone.utc), v))
    n = max(len(panels), 1)
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.6 * n + 0.6), sharex=True, squeeze=False)
    axes = axes[:, 0]
    if not panels:
        axes[0].text(0.5, 0.5, "no finished recording with a time", ha="center", va="center",
                     transform=axes[0].transAxes)
    for ax, (p, spec) in zip(axes, panels.items()):
        if spec["kind"] == "events":
            labels = sorted(spec["series"])
            for i, lab in enumerate(labels):
                ts = [t for t, _ in spec["series"][lab]]
                ax.plot(ts, [i] * len(ts), "o", label=lab)
            ax.set_yticks(range(len(labels)), labels)
            ax.set_ylim(-0.7, max(len(labels) - 0.3, 0.7))
        else:
            for lab, pts in spec["series"].items():
                xs, ys = [], []
                for t, v in pts:
                    for y in (v if isinstance(v, list) else [v]):
                        if y is not None and math.isfinite(y):
                            xs.append(t)
                            ys.append(float(y))
                if spec["relative"] and ys and ys[0] != 0.0:
                    ys = [y / ys[0] for y in ys]
                ax.plot(xs, ys, "o" if isinstance(pts[0][1], list) else "o-", ms=4, lw=0.8, label=lab)
            if len(spec["series"]) > 1:
                ax.legend(fontsize=7, ncol=min(len(spec["series"]), 4))
        ax.set_ylabel(p, fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("recording time (UTC)")
    fig.suptitle(title, fontsize=10)
    fig.autofmt_xdate()
    fig.tight_layout()
    return fig


_STYLE = ("body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;font-size:13px}"
          "td,th{border:1px solid #ccc;padding:3px 6px;text-align:left;vertical-align:top}"
          "tr.failed td{background:#fde8e8}th{background:#eee}img{max-width:100%}")


def _link_files(r: JobResult) -> list[str]:
    """The outputs worth a link, reports and figures first."""
    rank = {".html": 0, ".png": 1, ".json": 2, ".csv": 3, ".txt": 4}
    files = [f for f in r.files if Path(f).suffix in rank]
    return sorted(files, key=lambda f: (rank[Path(f).suffix], f))


def index_html(rows: list[dict], results: dict[str, JobResult], verb: str, metric_cols: list[str]) -> str:
    n_done = sum(r["status"] == "done" for r in rows)
    head = ["recording time (UTC)", "recording", "status", "kind", *metric_cols, "outputs", "error"]
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'>",
           f"<title>maglev-ros batch {html.escape(verb)}</title><style>{_STYLE}</style></head><body>",
           f"<h1>maglev-ros batch {html.escape(verb)}</h1>",
           f"<p>{n_done} of {len(rows)} recording(s) done, {len(rows) - n_done} failed. "
           "Table: <a href='summary.csv'>summary.csv</a>, <a href='summary.parquet'>summary.parquet</a>.</p>",
           "<h2>Trend over time</h2><p><img src='trend.png' alt='trend plot'></p>",
           "<h2>Recordings</h2><table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for row in rows:
        r = results[row["name"]]
        if r.status == "done":
            links = " ".join(f"<a href='{html.escape(r.name)}/{html.escape(f)}'>{html.escape(f)}</a>"
                             for f in _link_files(r))
        else:
            links = f"<a href='{html.escape(row['output'])}'>failure record</a>"
        cells = [row["recording_time_utc"], row["name"], row["status"], row["run_kind"] or "",
                 *[_fmt(row.get(c)) for c in metric_cols]]
        out.append(f"<tr class='{html.escape(row['status'])}'>"
                   + "".join(f"<td>{html.escape(str(c))}</td>" for c in cells)
                   + f"<td>{links}</td><td>{html.escape(row['error'] or '')}</td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out)


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.5g}"
    return str(v)


def write_summary(out: Path, results: list[JobResult], ran: set[str], verb: str) -> list[Path]:
    """Write the four summary files into ``out`` together; returns their paths."""
    import matplotlib.pyplot as plt
    rows = table_rows(results, ran)
    metric_cols = [c for c in _columns(rows) if c not in FIRST_COLUMNS and not c.endswith("_std")][:8]
    fig = trend_figure(results, f"maglev-ros batch {verb}: {len(rows)} recording(s)")
    try:
        with outputs.Batch() as b:
            b.write_text(out / "summary.csv", csv_text(rows), option="--out")
            b.write_bytes(out / "summary.parquet", parquet_bytes(rows), option="--out")
            b.write_figure(out / "trend.png", fig, "--out", dpi=100)
            b.write_text(out / "index.html", index_html(rows, {r.name: r for r in results}, verb, metric_cols),
                         option="--out")
    finally:
        plt.close(fig)
    return [out / f for f in FILES]

"""``humfall campaign report RESULTS``: one self-contained HTML page (PNG plots embedded).

Threshold map: the fall threshold per push direction and height (table and polar map),
and where the robot fell at the smallest falling push. Sweeps: fall rate by each design
key, the avoidance angle by push direction (polar, paper 1 Fig. 5's angle) when the
trials have one, histograms of fall time and of any lead-time metric. Always: status
counts, failed trials with their errors, timings and memory, and a per-column summary.
"""
from __future__ import annotations

import base64
import dataclasses
import html
import io
import math
import pathlib

import numpy as np
import pyarrow as pa

from humfall_ros.campaign.store import load_results


@dataclasses.dataclass
class Threshold:
    """One threshold-map cell.

    Attributes:
        cell: cell index; point: its design values (direction, height, ...).
        low: largest value whose trial kept the outcome False (None: none did) [N].
        high: smallest value whose trial gave the outcome True (None: none did) [N].
        threshold: mid-point of [low, high], None unless both were seen [N].
        status: ok | below_range | above_range | failed | incomplete.
        fall_direction_deg: where the robot fell at ``high`` [deg].
        trials: trials run for this cell.
    """

    cell: int
    point: dict
    low: float | None
    high: float | None
    threshold: float | None
    status: str
    fall_direction_deg: float | None
    trials: int


def thresholds(table: pa.Table, spec: dict) -> list[Threshold]:
    study = spec["study"]
    key, outcome = f"set.{study['key']}", f"m.{study.get('outcome', 'fell')}"
    steps = _max_steps(study)
    rows = table.to_pylist()
    design_cols = [c for c in table.column_names if c.startswith("set.") and c != key]
    cells: dict[int, list] = {}
    for r in rows:
        cells.setdefault(int(r["cell"]), []).append(r)
    out = []
    for c, rs in sorted(cells.items()):
        rs.sort(key=lambda r: r["step"])
        ok = [r for r in rs if r["status"] == "ok" and r.get(outcome) is not None]
        lows = [r[key] for r in ok if not r[outcome]]
        highs = [r for r in ok if r[outcome]]
        low = max(lows) if lows else None
        hr = min(highs, key=lambda r: r[key]) if highs else None
        high = hr[key] if hr else None
        if len(ok) < len(rs):
            status = "failed"
        elif len(rs) < steps:
            status = "incomplete"
        elif low is None:
            status = "below_range"
        elif high is None:
            status = "above_range"
        else:
            status = "ok"
        thr = 0.5 * (low + high) if low is not None and high is not None else None
        out.append(Threshold(c, {k[4:]: rs[0][k] for k in design_cols}, low, high, thr, status,
                             hr.get("m.fall_direction_deg") if hr else None, len(rs)))
    return out


def _max_steps(study: dict) -> int:
    steps, width = 0, study["high"] - study["low"]
    while width > study.get("tolerance", 5.0):
        width /= 2.0
        steps += 1
    return steps


# ---------------------------------------------------------------------------- plots
def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _polar(groups: dict, title: str, rlabel: str) -> str:
    """groups: label -> (directions [deg], values); a closed line per group."""
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(5.5, 5.5))
    ax = fig.add_subplot(projection="polar")
    for label, (d, v) in groups.items():
        order = np.argsort(d)
        d, v = np.asarray(d, float)[order], np.asarray(v, float)[order]
        if len(d) > 2:
            d, v = np.append(d, d[0]), np.append(v, v[0])
        ax.plot(np.radians(d), v, "o-", label=str(label))
    ax.set_theta_zero_location("N")   # 0 deg (forward, +x) up, 90 deg (left, +y) to the left
    ax.set_title(title)
    ax.text(0.0, -0.08, rlabel, transform=ax.transAxes, fontsize=8)
    ax.legend(loc="upper right", bbox_to_anchor=(1.3, 1.1), fontsize=8)
    return _png(fig)


def _hist(values, title: str, xlabel: str) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    ax.hist(values, bins=min(40, max(5, int(math.sqrt(len(values))))))
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("trials")
    return _png(fig)


def _rate_plot(x, fell, key: str) -> str:
    import matplotlib.pyplot as plt

    x = np.asarray(x, float)
    fell = np.asarray(fell, float)
    uniq = np.unique(x)
    if len(uniq) > 12:
        edges = np.linspace(x.min(), x.max(), 13)
        idx = np.clip(np.digitize(x, edges) - 1, 0, 11)
        centres = 0.5 * (edges[:-1] + edges[1:])
        rate = [fell[idx == i].mean() if np.any(idx == i) else np.nan for i in range(12)]
    else:
        centres = uniq
        rate = [fell[x == u].mean() for u in uniq]
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    ax.plot(centres, rate, "o-")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel(key)
    ax.set_ylabel("fall rate")
    ax.set_title(f"fall rate by {key}")
    return _png(fig)


# ---------------------------------------------------------------------------- page
def _table_html(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return "" if math.isnan(v) else f"{v:.4g}"
        return html.escape("" if v is None else str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _numeric(table: pa.Table, col: str) -> np.ndarray:
    vals = table.column(col).to_pylist()
    return np.array([float(v) if isinstance(v, (int, float)) and v is not None else np.nan for v in vals])


def column_summary(table: pa.Table) -> list[list]:
    out = []
    for c in table.column_names:
        t = table.schema.field(c).type
        if pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t):
            v = _numeric(table, c) if not pa.types.is_boolean(t) else np.array(
                [np.nan if x is None else float(x) for x in table.column(c).to_pylist()])
            f = v[np.isfinite(v)]
            out.append([c, str(t), len(f), f.mean() if len(f) else None, f.min() if len(f) else None,
                        f.max() if len(f) else None])
        else:
            out.append([c, str(t), table.num_rows - table.column(c).null_count, None, None, None])
    return out


def write_report(results: str | pathlib.Path, out: str | pathlib.Path | None = None) -> pathlib.Path:
    table, meta = load_results(results)
    spec = meta.get("spec") or {}
    res_path = pathlib.Path(results)
    out = pathlib.Path(out) if out else (res_path if res_path.is_dir() else res_path.parent) / "report.html"
    parts = [f"<h1>Campaign {html.escape(spec.get('name', '?'))}</h1>",
             f"<p>{html.escape(spec.get('description', ''))}</p>",
             (f"<p>base scenario <code>{html.escape(str(spec.get('base_scenario')))}</code>, study "
              f"<code>{html.escape(str((spec.get('study') or {}).get('type')))}</code>, spec hash "
              f"<code>{html.escape(str(meta.get('spec_hash', ''))[:16])}</code>, {table.num_rows} trials</p>")]
    status = table.column("status").to_pylist()
    counts = {s: status.count(s) for s in sorted(set(status), key=str)}
    parts.append("<h2>Status</h2>" + _table_html(["status", "trials"], [[k, v] for k, v in counts.items()]))
    cols = table.column_names
    study = spec.get("study") or {}
    if study.get("type") == "threshold-map" and "cell" in cols:
        parts.append(_threshold_section(table, spec))
    else:
        parts.append(_sweep_section(table, spec))
    if "m.fall_time_s" in cols:
        v = _numeric(table, "m.fall_time_s")
        v = v[np.isfinite(v)]
        if len(v):
            parts.append(f'<img src="data:image/png;base64,{_hist(v, "fall time", "fall_time_s [s]")}">')
    for c in cols:
        if "lead_time" in c:
            v = _numeric(table, c)
            v = v[np.isfinite(v)]
            if len(v):
                parts.append(f'<h3>{html.escape(c)}</h3><img src="data:image/png;base64,{_hist(v, c, c)}">')
    parts.append(_timing_section(table, meta))
    bad = [r for r in table.to_pylist() if r["status"] != "ok"]
    if bad:
        parts.append("<h2>Trials that did not finish</h2>" + _table_html(
            ["trial", "status", "error", "log tail (last line)"],
            [[r["trial_id"], r["status"], (r.get("error") or "")[:300],
              (r.get("log_tail") or "").strip().splitlines()[-1:] or ""] for r in bad[:200]]))
    parts.append("<h2>Columns</h2>" + _table_html(["column", "type", "values", "mean", "min", "max"],
                                                  column_summary(table)))
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto} table{border-collapse:collapse;"
             "margin:8px 0} td,th{border:1px solid #ccc;padding:2px 6px;font-size:12px} img{margin:6px}")
    out.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>campaign "
                   f"{html.escape(spec.get('name', ''))}</title><style>{style}</style></head><body>"
                   + "\n".join(parts) + "</body></html>")
    return out


def _direction_key(point: dict) -> str | None:
    return next((k for k in point if k.endswith("direction_deg")), None)


def _threshold_section(table: pa.Table, spec: dict) -> str:
    th = thresholds(table, spec)
    if not th:
        return "<p>no cells</p>"
    keys = list(th[0].point)
    dkey = _direction_key(th[0].point)
    others = [k for k in keys if k != dkey]
    parts = [(f"<h2>Fall threshold ({html.escape(spec['study']['key'])}, to "
              f"{spec['study'].get('tolerance', 5)} N)</h2>")]
    parts.append(_table_html([*keys, "low (held)", "high (fell)", "threshold", "status", "fall direction [deg]",
                              "trials"],
                             [[*[t.point[k] for k in keys], t.low, t.high, t.threshold, t.status,
                               t.fall_direction_deg, t.trials] for t in th]))
    if dkey:
        groups, falls = {}, {}
        for t in th:
            label = ", ".join(f"{k.split('.')[-1]}={t.point[k]:g}" if isinstance(t.point[k], float)
                              else f"{k}={t.point[k]}" for k in others) or "all"
            if t.threshold is not None:
                groups.setdefault(label, ([], []))
                groups[label][0].append(t.point[dkey])
                groups[label][1].append(t.threshold)
            if t.fall_direction_deg is not None:
                falls.setdefault(label, ([], []))
                falls[label][0].append(t.point[dkey])
                falls[label][1].append(t.fall_direction_deg % 360.0)
        if groups:
            png = _polar(groups, "fall threshold by push direction (0° forward, 90° left)", "radius: threshold [N]")
            parts.append(f'<img src="data:image/png;base64,{png}">')
        if falls:
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(5.5, 4))
            for label, (d, f) in falls.items():
                ax.plot(d, f, "o", label=label)
            ax.plot([0, 360], [0, 360], "k:", lw=0.8)
            ax.set_xlabel("push direction [deg]")
            ax.set_ylabel("fall direction at the threshold [deg]")
            ax.set_title("where the robot falls (paper 1 §II-C: edge normals)")
            ax.legend(fontsize=8)
            parts.append(f'<img src="data:image/png;base64,{_png(fig)}">')
    return "\n".join(parts)


def _sweep_section(table: pa.Table, spec: dict) -> str:
    cols = table.column_names
    parts = ["<h2>Outcomes by design key</h2>"]
    ok = [i for i, s in enumerate(table.column("status").to_pylist()) if s == "ok"]
    if not ok or "m.fell" not in cols:
        return "<p>no finished trials with a fall outcome</p>"
    t = table.take(pa.array(ok))
    fell = [bool(x) for x in t.column("m.fell").to_pylist()]
    for c in cols:
        if c.startswith("set.") and (pa.types.is_integer(t.schema.field(c).type)
                                     or pa.types.is_floating(t.schema.field(c).type)):
            parts.append(f'<img src="data:image/png;base64,{_rate_plot(_numeric(t, c), fell, c[4:])}">')
    dcol = next((c for c in cols if c.startswith("set.") and c.endswith("direction_deg")), None)
    group_col = "set.controller" if "set.controller" in cols else None
    groups = [str(g) for g in t.column(group_col).to_pylist()] if group_col else ["mean"] * t.num_rows
    for metric, name in (("m.avoidance_angle_deg", "avoidance angle α (at the CoP when the push began)"),
                         ("m.avoidance_angle_p2_deg", "avoidance angle α2 (paper 1 Fig. 5: CoP after the step)")):
        if not dcol or metric not in cols:
            continue
        d, a = _numeric(t, dcol), _numeric(t, metric)
        m = np.isfinite(d) & np.isfinite(a)
        if not m.any():
            continue
        bins = np.round(d / 30.0) * 30.0 % 360.0
        lines = {}
        for g in sorted(set(groups)):
            sel = m & np.array([x == g for x in groups])
            dirs = sorted(set(bins[sel]))
            if dirs:
                lines[g] = (dirs, [a[sel & (bins == b)].mean() for b in dirs])
        parts.append(f"<h3>Mean {name} by push direction</h3>")
        parts.append(f'<img src="data:image/png;base64,{_polar(lines, name.split(" (")[0], "radius: deg")}">')
    parts.append(_cross_table(t, fell, [c for c in cols if c.startswith("set.")]))
    return "\n".join(parts)


def _cross_table(t: pa.Table, fell: list[bool], keys: list[str]) -> str:
    """Trials and falls for each pair of values of the first two design keys (e.g. e-stop speed x phase)."""
    if len(keys) < 2:
        return ""
    a, b = (t.column(k).to_pylist() for k in keys[:2])
    def order(v):  # numbers by value, then everything else by its text
        return (0, float(v), "") if isinstance(v, (int, float)) and not isinstance(v, bool) else (1, 0.0, str(v))

    rows, cols_ = sorted(set(a), key=order), sorted(set(b), key=order)
    if len(rows) * len(cols_) > 400:
        return ""
    cell = {}
    for x, y, f in zip(a, b, fell):
        n, k = cell.get((x, y), (0, 0))
        cell[(x, y)] = (n + 1, k + int(f))
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols_)
    body = "".join("<tr><th>" + html.escape(str(r)) + "</th>" + "".join(
        f"<td>{cell[(r, c)][1]} / {cell[(r, c)][0]}</td>" if (r, c) in cell else "<td></td>" for c in cols_)
        + "</tr>" for r in rows)
    return (f"<h3>Fell / trials: {html.escape(keys[0][4:])} (rows) × {html.escape(keys[1][4:])} (columns)</h3>"
            f"<table><tr><th></th>{head}</tr>{body}</table>")


def _timing_section(table: pa.Table, meta: dict) -> str:
    rows = []
    for c, unit in (("wall_s", "s"), ("cpu_s", "s"), ("server_hwm_mb", "MB"), ("worker_rss_mb", "MB")):
        if c in table.column_names:
            v = _numeric(table, c)
            v = v[np.isfinite(v)]
            if len(v):
                rows.append([f"{c} [{unit}]", np.median(v), np.percentile(v, 90), v.max(), v.sum()])
    sessions = meta.get("sessions", [])
    srows = [[s.get("started"), s.get("ended"), s.get("executor"), s.get("workers"), s.get("ran"),
              s.get("resumed_trials"), s.get("wall_s"), s.get("interrupted")] for s in sessions]
    return ("<h2>Timings and memory per trial</h2>" + _table_html(["", "median", "p90", "max", "sum"], rows)
            + "<h3>Sessions</h3>" + _table_html(["started", "ended", "executor", "workers", "trials run",
                                                 "resumed", "wall [s]", "interrupted"], srows))

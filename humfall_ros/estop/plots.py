"""E-stop plots in the style of paper 3's figures, from an in-process run or from a bag. No rclpy, no simulator.

* :func:`plot_axes` -- Fig. 4 / 5 style: ZMP and CoG over time along the Minor axis (x) and the Major axis
  (y) of the stop frame, plan (walking's pattern before the stop, the stop's references after it) against
  the measured ones (the estimator's CoG and CoP, what ``centroidal_state`` carries); the stop's start and
  n3 marked.
* :func:`plot_locus` -- Fig. 10 style: the XY locus of the CoG and the CoP (measured and planned) with the
  double-support polygon of the stop.
* :func:`plot_displacement` -- Fig. 7 style: maximum Major-axis displacement (n3 planned and the measured
  maximum) and the Minor-axis maximum ZMP against walking speed, from a trial table.

Data: :class:`EstopRun`, built by :func:`run_from_trace` (a dict of per-tick arrays, e.g.
benchmarks/estop_trials.py's trace or its saved .npz) or by :func:`run_from_bag` (``/centroidal_state``,
``/estop/status`` and, when recorded, ``/walking/state``). Matplotlib's object API on the Agg canvas (no
display, no pyplot state).
"""
from __future__ import annotations

import dataclasses
import math
import os
import pathlib

import numpy as np


@dataclasses.dataclass
class EstopRun:
    """Per-tick series of one run (world frame) and the stop's frame.

    Attributes:
        t: tick times [s] (n,).
        com, cop: measured CoG and CoP [m] (n, 3).
        com_ref, zmp_ref: planned CoG and ZMP [m] (n, 3) (NaN where unknown).
        frame_origin, frame_major: the stop frame's origin and unit Major axis, world xy (2,).
        start: sim time the stop started [s].
        polygon: double-support polygon of the stop [m] (k, 2).
        n3: planned maximum Major displacement [m] (eq. 21).
        label: title text.
    """

    t: np.ndarray
    com: np.ndarray
    cop: np.ndarray
    com_ref: np.ndarray
    zmp_ref: np.ndarray
    frame_origin: np.ndarray
    frame_major: np.ndarray
    start: float
    polygon: np.ndarray
    n3: float = math.nan
    label: str = ""

    @property
    def frame_minor(self) -> np.ndarray:
        m = self.frame_major
        return np.array([m[1], -m[0]])

    def local(self, p: np.ndarray) -> np.ndarray:
        """World xy (..., 2+) -> (minor x, major y) [m]."""
        d = np.asarray(p, float)[..., :2] - self.frame_origin
        return np.stack([d @ self.frame_minor, d @ self.frame_major], axis=-1)


def _plan(primary: np.ndarray, fallback: np.ndarray | None) -> np.ndarray:
    """The stop's references where known, else (before the start) walking's."""
    out = np.array(primary, float, copy=True)
    if fallback is not None:
        bad = ~np.isfinite(out).all(axis=1)
        out[bad] = np.asarray(fallback, float)[bad]
    return out


def run_from_trace(tr, label: str = "", cop_key: str = "cop") -> EstopRun:
    """From a dict / npz of per-tick arrays: ``t, com, cop, estop_com_ref, estop_zmp_ref`` and optionally
    ``com_ref, zmp_ref, walking`` (walking's references), plus ``frame_origin, frame_major, start, polygon, n3``;
    ``cop_key`` names the measured CoP series (e.g. ``cop_truth``: the trial harness's tick-averaged CoP)."""
    g = tr.get if hasattr(tr, "get") else (lambda k, d=None: tr[k] if k in tr else d)
    walking = g("walking")
    wc, wz = g("com_ref"), g("zmp_ref")
    if walking is not None and wc is not None:
        w = np.asarray(walking, bool)
        wc = np.where(w[:, None], wc, np.nan)
        wz = np.where(w[:, None], wz, np.nan)
    return EstopRun(np.asarray(tr["t"], float), np.asarray(tr["com"], float), np.asarray(tr[cop_key], float),
                    _plan(tr["estop_com_ref"], wc), _plan(tr["estop_zmp_ref"], wz),
                    np.asarray(tr["frame_origin"], float), np.asarray(tr["frame_major"], float),
                    float(tr["start"]), np.asarray(tr["polygon"], float).reshape(-1, 2), float(g("n3", math.nan)),
                    label)


def run_from_bag(bag: str | os.PathLike, label: str = "") -> EstopRun:
    """From a run's bag (humfall_ros.recording): the measured series from ``/centroidal_state``, the stop's
    references, frame and start from ``/estop/status``, walking's references from ``/walking/state`` if any.
    The polygon is the measured support polygon at the stop's start. Raises ValueError without a stop."""
    from humfall_ros.recording.reader import read_messages, resolve_bag

    def stamp(m) -> int:
        return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

    def v(p) -> tuple:
        return (p.x, p.y, p.z)

    cs, st, ws = {}, {}, {}
    topics = ["/centroidal_state", "/estop/status", "/walking/state"]
    for raw, m in read_messages(resolve_bag(bag), topics):
        k = stamp(m)
        if raw.topic == "/centroidal_state":
            cs[k] = (v(m.com), v(m.cop), [(p.x, p.y) for p in m.support_polygon])
        elif raw.topic == "/estop/status":
            st[k] = m
        elif bool(getattr(m, "walking", False)):
            ws[k] = (v(m.com_ref), v(m.zmp_ref))
    started = [m for m in st.values() if math.isfinite(m.start_time)]
    if not started:
        raise ValueError(f"{bag}: no e-stop started (no /estop/status with a start_time)")
    last = started[-1]
    keys = sorted(cs)
    nan3 = (math.nan,) * 3
    start_key = min(keys, key=lambda k: abs(k * 1e-9 - last.start_time))
    er = [st.get(k) for k in keys]
    return EstopRun(
        np.array(keys, float) * 1e-9, np.array([cs[k][0] for k in keys]), np.array([cs[k][1] for k in keys]),
        _plan(np.array([v(m.com_ref) if m is not None else nan3 for m in er]),
              np.array([ws.get(k, (nan3, nan3))[0] for k in keys])),
        _plan(np.array([v(m.zmp_ref) if m is not None else nan3 for m in er]),
              np.array([ws.get(k, (nan3, nan3))[1] for k in keys])),
        np.array([last.frame_origin.x, last.frame_origin.y]), np.array([last.major_axis.x, last.major_axis.y]),
        float(last.start_time), np.array(cs[start_key][2], float).reshape(-1, 2), float(last.n_major[2]), label)


# ---------------------------------------------------------------------- figures
def _figure(rows: int, cols: int, size):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    return fig, [[fig.add_subplot(rows, cols, r * cols + c + 1) for c in range(cols)] for r in range(rows)]


def _save(fig, path) -> pathlib.Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    fig.tight_layout()
    path = pathlib.Path(path)
    fig.savefig(path)
    return path


def plot_axes(run: EstopRun, path, before: float = 1.0, after: float = 3.0) -> pathlib.Path:
    """Fig. 4 / 5 style (module docstring): 2 x 2 panels, rows Minor / Major axis, columns ZMP / CoG,
    time from ``before`` [s] ahead of the stop's start to ``after`` [s] past it."""
    sel = (run.t >= run.start - before) & (run.t <= run.start + after)
    t = run.t[sel] - run.start
    meas = {"ZMP": run.local(run.cop[sel]), "CoG": run.local(run.com[sel])}
    plan = {"ZMP": run.local(run.zmp_ref[sel]), "CoG": run.local(run.com_ref[sel])}
    fig, ax = _figure(2, 2, (11, 7))
    for r, axis in enumerate(("Minor (x)", "Major (y)")):
        for c, what in enumerate(("ZMP", "CoG")):
            a = ax[r][c]
            a.plot(t, meas[what][:, r], color="tab:blue", lw=1.0, label=f"measured {'CoP' if what == 'ZMP' else what}")
            a.plot(t, plan[what][:, r], color="tab:red", lw=1.4, ls="--", label=f"planned {what}")
            a.axvline(0.0, color="0.5", lw=0.8)
            if r == 1 and math.isfinite(run.n3):
                a.axhline(run.n3, color="tab:green", lw=0.8, ls=":", label="n3")
            a.set_xlabel("time from the stop's start [s]")
            a.set_ylabel(f"{what} {axis} [m]")
            a.grid(alpha=0.3)
            a.legend(fontsize=8, loc="best")
    fig.suptitle(run.label or "e-stop: ZMP and CoG per axis")
    return _save(fig, path)


def plot_locus(run: EstopRun, path, before: float = 1.0, after: float = 3.0) -> pathlib.Path:
    """Fig. 10 style: XY locus of CoG and CoP (measured, planned) with the double-support polygon."""
    sel = (run.t >= run.start - before) & (run.t <= run.start + after)
    fig, ax = _figure(1, 1, (7, 7))
    a = ax[0][0]
    poly = np.vstack([run.polygon, run.polygon[:1]]) if len(run.polygon) else np.zeros((0, 2))
    if len(poly):
        a.fill(poly[:, 0], poly[:, 1], color="0.85", label="double-support polygon")
        a.plot(poly[:, 0], poly[:, 1], color="0.4", lw=0.8)
    a.plot(run.cop[sel, 0], run.cop[sel, 1], color="tab:blue", lw=0.7, alpha=0.7, label="measured CoP")
    a.plot(run.com[sel, 0], run.com[sel, 1], color="k", lw=1.4, label="measured CoG")
    a.plot(run.zmp_ref[sel, 0], run.zmp_ref[sel, 1], color="tab:red", lw=1.0, ls="--", label="planned ZMP")
    a.plot(run.com_ref[sel, 0], run.com_ref[sel, 1], color="tab:orange", lw=1.0, ls="--", label="planned CoG")
    k = int(np.argmin(np.abs(run.t - run.start)))
    a.plot(*run.com[k, :2], "o", color="k", ms=5, label="CoG at the start")
    o, mj = run.frame_origin, run.frame_major
    a.annotate("", xy=o + 0.1 * mj, xytext=o, arrowprops={"arrowstyle": "->", "color": "tab:green"})
    a.text(*(o + 0.11 * mj), "Major", color="tab:green", fontsize=8)
    a.set_aspect("equal", adjustable="datalim")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.grid(alpha=0.3)
    a.legend(fontsize=8, loc="best")
    a.set_title(run.label or "e-stop: CoG and CoP locus")
    return _save(fig, path)


def plot_displacement(rows: list[dict], path) -> pathlib.Path:
    """Fig. 7 style: against walking speed, |n3| planned and the measured maximum Major displacement, and
    the predicted / measured Minor-axis maximum ZMP (rows: benchmarks/estop_trials.py's table)."""
    fig, ax = _figure(1, 2, (11, 4.5))
    done = [r for r in rows if r.get("n3_m") is not None]
    for phase in sorted({r["phase"] for r in done}):
        rs = sorted((r for r in done if r["phase"] == phase), key=lambda r: r["speed_kmh"])
        v = [r["speed_kmh"] for r in rs]
        line = ax[0][0].plot(v, [abs(r["n3_m"]) for r in rs], "o-", label=f"{phase}: |n3|")[0]
        ax[0][0].plot(v, [r.get("max_displacement_m") or np.nan for r in rs], "x--", color=line.get_color(),
                      label=f"{phase}: measured")
        line = ax[0][1].plot(v, [abs(r.get("predicted_max_zmp_minor_m") or np.nan) for r in rs], "o-",
                             label=f"{phase}: predicted")[0]
        ax[0][1].plot(v, [r.get("max_cop_minor_m") or np.nan for r in rs], "x--", color=line.get_color(),
                      label=f"{phase}: measured CoP")
    ax[0][0].set_ylabel("maximum Major displacement [m]")
    ax[0][1].set_ylabel("maximum Minor ZMP displacement [m]")
    ax[0][1].axhline(0.022, color="0.5", ls=":", lw=0.8, label="paper 1.8 km/h: 0.022 m")
    for a in ax[0]:
        a.set_xlabel("walking speed [km/h]")
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc="best")
    return _save(fig, path)


def plot_run(run: EstopRun, out_dir, stem: str = "estop") -> list[pathlib.Path]:
    """Both per-run figures into ``out_dir`` (``<stem>_axes.png``, ``<stem>_locus.png``)."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [plot_axes(run, out / f"{stem}_axes.png"), plot_locus(run, out / f"{stem}_locus.png")]


__all__ = ["EstopRun", "plot_axes", "plot_displacement", "plot_locus", "plot_run", "run_from_bag", "run_from_trace"]

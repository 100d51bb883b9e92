"""Safe-fall figures like paper 1's: Fig. 9 (support polygons, CoP and reference points per phase),
Fig. 11 (CoM paths and the avoidance angle over time, per controller) and the sweep's polar plot.

Inputs are ``sim.fall_runs.FallRun`` objects (run with ``keep_trace=True``) and ``sim.fall_sweep`` rows.
Matplotlib with the Agg backend; each function writes one PNG and returns its path.
"""
from __future__ import annotations

import math
import pathlib

import numpy as np

COLORS = {"none": "tab:gray", "stepping": "tab:blue", "stepping_inertia": "tab:red"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _closed(poly):
    p = np.asarray(poly, float).reshape(-1, 2)
    return np.vstack([p, p[:1]]) if len(p) else p


def _target_box(ax, sc_obstacles):
    for o in sc_obstacles or []:
        if not o.get("is_target"):
            continue
        x, y = o["position"][:2]
        sx, sy = o["size"][:2]
        c, s = math.cos(o.get("yaw", 0.0)), math.sin(o.get("yaw", 0.0))
        local = np.array([[sx, sy], [-sx, sy], [-sx, -sy], [sx, -sy]]) / 2
        pts = local @ np.array([[c, s], [-s, c]]) + [x, y]
        ax.fill(*_closed(pts).T, color="orange", alpha=0.4, label="target T")
        return np.array([x, y])
    return None


def fig9(run, obstacles, path) -> pathlib.Path:
    """Paper 1 Fig. 9: the support before and after the step, P1, Q1, predicted P2, Q2, measured P2, CoM path."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 6))
    d, res = run.decision, run.search
    if res is not None:
        from humfall_ros.fall.step_search import StepCase

        before = res.cases.get(StepCase.NO_CHANGE)
        if before is not None:
            ax.plot(*_closed(before.polygon).T, "k-", lw=1.5, label="support at the decision")
        if res.best is not None and res.best.polygon is not None:
            ax.fill(*_closed(run.search.best.polygon).T, color="tab:blue", alpha=0.15,
                    label=f"new support ({res.best.case.value}, decided)")
    if d is not None:
        ax.plot(*d.p1, "ks", label="P1 (CoP)")
        ax.plot(*d.q1, "k^", label="Q1 (capture point)")
        ax.plot(*d.p2, "bs", mfc="none", label="P2 predicted")
        ax.plot(*d.q2, "b^", mfc="none", label="Q2 predicted")
        if np.all(np.isfinite(d.landing)):
            x, y, yaw = d.landing
            c, s = math.cos(yaw), math.sin(yaw)
            local = np.array([[0.145, 0.07], [-0.095, 0.07], [-0.095, -0.07], [0.145, -0.07]])
            ax.plot(*_closed(local @ np.array([[c, s], [-s, c]]) + [x, y]).T, "b--", lw=1, label="landing sole")
    m = run.metrics
    if m.get("measured_p2"):
        ax.plot(*m["measured_p2"], "rs", label="P2 measured")
    if run.trace:
        com = np.array([t[1][:2] for t in run.trace])
        ax.plot(com[:, 0], com[:, 1], "g-", lw=1, label="CoM path")
        cop = np.array([t[3][:2] for t in run.trace if t[3] is not None])
        if len(cop):
            ax.plot(cop[:, 0], cop[:, 1], ".", color="tab:purple", ms=1.5, label="CoP (ground truth)")
    T = _target_box(ax, obstacles)
    if T is not None and d is not None:
        for p, c in ((d.p1, "k"), (d.p2, "b")):
            ax.plot([p[0], T[0]], [p[1], T[1]], c + ":", lw=0.8)
    a2 = m.get("avoidance_angle_p2_deg")
    ax.set_title(f"standing push: decision and outcome (alpha2 measured {a2:.0f} deg)" if a2 is not None
                 else "decision and outcome")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3)
    path = pathlib.Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def fig11(runs: dict, obstacles, path) -> pathlib.Path:
    """Paper 1 Fig. 11: CoM ground paths per controller and the avoidance angle at P over time."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.8))
    T = _target_box(a1, obstacles)
    for kind, r in runs.items():
        if not r.trace:
            continue
        land = r.metrics.get("landing_time_s")
        keep = [x for x in r.trace if land is None or x[0] <= land + 0.05]  # until the trunk lands (no rebound)
        t = np.array([x[0] for x in keep])
        com = np.array([x[1][:2] for x in keep])
        c = COLORS.get(kind, None)
        a1.plot(com[:, 0], com[:, 1], color=c, label=kind)
        p0 = r.metrics.get("initial_cop")
        if T is not None and p0 is not None:
            p0 = np.asarray(p0)
            u, v = com - p0, T - p0
            nu = np.linalg.norm(u, axis=1)
            ang = np.degrees(np.arccos(np.clip(u @ v / np.maximum(nu * np.linalg.norm(v), 1e-12), -1, 1)))
            ok = nu > 0.03  # the angle means nothing while the CoM is over P
            a2.plot(t[ok], ang[ok], color=c, label=kind)
        ev = r.metrics.get("fall_event_time_s")
        if ev is not None:
            a2.axvline(ev, color=c, ls=":", lw=0.8)
    a1.set_aspect("equal")
    a1.set_xlabel("x [m]")
    a1.set_ylabel("y [m]")
    a1.set_title("CoM ground path")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    a2.set_xlabel("t [s]")
    a2.set_ylabel("avoidance angle at P [deg]")
    a2.set_ylim(0, 180)
    a2.set_title("avoidance angle over time (dotted: fall event)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    path = pathlib.Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def sweep_polar(rows: list[dict], path, key: str = "avoidance_angle_p2_deg") -> pathlib.Path:
    """Avoidance angle (alpha2; alpha where alpha2 is undefined) against the push direction, per controller."""
    plt = _plt()
    fig = plt.figure(figsize=(7.5, 6))
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_direction(-1)
    for kind in ("none", "stepping", "stepping_inertia"):
        rs = sorted((r for r in rows if r["controller"] == kind), key=lambda r: r["push_angle_deg"])
        if not rs:
            continue
        th = [math.radians(r["push_angle_deg"]) for r in rs]  # pushes clockwise from +x (the axes turn clockwise)
        val = [r[key] if r.get(key) is not None else r.get("avoidance_angle_deg") for r in rs]
        val = [np.nan if v is None else v for v in val]
        ax.plot(th + th[:1], val + val[:1], "o-", color=COLORS[kind], label=kind)
        # a capture has no avoidance angle: a hollow marker on the rim; a target hit (< 5 cm) a cross
        cap = [t for t, r in zip(th, rs) if r.get("fell") is False]
        if cap:
            ax.plot(cap, [180.0] * len(cap), "o", mfc="none", ms=9, color=COLORS[kind], label=f"{kind}: captured")
        hit = [(t, v) for t, v, r in zip(th, val, rs)
               if r.get("fell") and (r.get("min_target_distance_m") or 0.0) < 0.05 and np.isfinite(v)]
        if hit and kind != "none":
            ax.plot(*zip(*hit), "x", ms=10, mew=2, color=COLORS[kind], label=f"{kind}: target hit")
    ax.set_rlim(0, 180)
    ax.set_title("avoidance angle alpha2 [deg] by push direction\n(pushes clockwise from the robot's forward +x)",
                 fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.05, 1.0))
    path = pathlib.Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


__all__ = ["fig11", "fig9", "sweep_polar"]

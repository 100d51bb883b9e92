"""PNG plots of a run from its bag (``humfall bag plot`` and the launcher's end-of-run plots).

From ``centroidal_state`` (humfall_interfaces/msg/CentroidalState):
  ``top_view.png``        ground-plane paths of the CoM projection, the CoP and the
                          capture point, the support polygon sampled over time, and the
                          obstacles (last ``obstacles`` ObstacleArray, target in red)
  ``centroidal_time.png`` lean angle, CoM height and CoM speed over time
From ``joint_states`` (sensor_msgs/JointState):
  ``joint_positions.png`` every joint position over time
From ``sim/result`` (std_msgs/String, the bridge's ground-truth metrics, JSON):
  ``fall_geometry.png``   paper 1 Fig. 5 for the run: initial CoP P, target T, the
                          CoM where the trunk landed, and the avoidance angle at P

Time axis: the message header stamp (sim time), or the bag's log time when a
stamp is zero, relative to the first sample. Messages that do not decode are
skipped (``reader.read_messages``). Uses matplotlib's object API with the Agg
canvas, so it needs no display and touches no global pyplot state.
"""
from __future__ import annotations

import json
import math
import os
import pathlib
import sys
from typing import Any

from humfall_ros.recording.reader import DecodeErrors, read_messages, resolve_bag

CENTROIDAL_TOPIC = "/centroidal_state"
OBSTACLES_TOPIC = "/obstacles"
JOINT_STATES_TOPIC = "/joint_states"
RESULT_TOPIC = "/sim/result"
POLYGON_SAMPLES = 8          # support polygons drawn along the run
MAX_POINTS = 5000            # longer series are strided for plotting


def _stamp_s(raw, msg) -> float:
    st = getattr(getattr(msg, "header", None), "stamp", None)
    if st is not None and (st.sec or st.nanosec):
        return st.sec + st.nanosec * 1e-9
    return raw.log_time * 1e-9


def _stride(n: int) -> int:
    return max(1, math.ceil(n / MAX_POINTS))


def load_series(bag: pathlib.Path) -> dict[str, Any]:
    """One pass over the bag: centroidal samples, last obstacle set, joint positions."""
    errors = DecodeErrors()
    cs: dict[str, list] = {k: [] for k in ("t", "com", "vel", "cop", "cp", "cpf", "poly", "lean")}
    obstacles: list[Any] = []
    js_t: list[float] = []
    js_pos: dict[str, list[tuple[float, float]]] = {}
    result: dict[str, Any] | None = None
    topics = [CENTROIDAL_TOPIC, OBSTACLES_TOPIC, JOINT_STATES_TOPIC, RESULT_TOPIC]
    for raw, msg in read_messages(bag, topics, errors):
        try:
            if raw.topic == CENTROIDAL_TOPIC:
                cs["t"].append(_stamp_s(raw, msg))
                cs["com"].append((msg.com.x, msg.com.y, msg.com.z))
                cs["vel"].append((msg.com_velocity.x, msg.com_velocity.y, msg.com_velocity.z))
                cs["cop"].append((msg.cop.x, msg.cop.y))
                cs["cp"].append((msg.capture_point.x, msg.capture_point.y))
                cpf = getattr(msg, "capture_point_fused", None)   # bags before session 17 lack it
                cs["cpf"].append((cpf.x, cpf.y) if cpf is not None else (math.nan, math.nan))
                cs["poly"].append([(p.x, p.y) for p in msg.support_polygon])
                cs["lean"].append(msg.lean_angle)
            elif raw.topic == OBSTACLES_TOPIC:
                obstacles = list(msg.obstacles)
            elif raw.topic == RESULT_TOPIC:
                result = json.loads(msg.data)
            else:
                t = _stamp_s(raw, msg)
                js_t.append(t)
                for name, pos in zip(msg.name, msg.position):
                    js_pos.setdefault(name, []).append((t, pos))
        except (AttributeError, TypeError, ValueError) as exc:  # not the fields (or JSON) we expect
            errors.add(raw.topic, exc)
    return {"centroidal": cs, "obstacles": obstacles, "joints": js_pos, "result": result, "errors": errors}


def _figure(rows: int = 1, size=(8, 6)):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    axes = [fig.add_subplot(rows, 1, i + 1) for i in range(rows)]
    return fig, axes


def _save(fig, path: pathlib.Path) -> pathlib.Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    fig.tight_layout()
    fig.savefig(path)
    return path


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def _box_corners(ob) -> list[tuple[float, float]]:
    c, s = math.cos(_yaw(ob.pose.orientation)), math.sin(_yaw(ob.pose.orientation))
    hx, hy = ob.size.x / 2, ob.size.y / 2
    px, py = ob.pose.position.x, ob.pose.position.y
    return [(px + c * dx - s * dy, py + s * dx + c * dy)
            for dx, dy in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy))]


def plot_top_view(cs: dict[str, list], obstacles: list[Any], path: pathlib.Path) -> pathlib.Path:
    from matplotlib.patches import Polygon

    fig, (ax,) = _figure(size=(8, 7))
    k = _stride(len(cs["t"]))
    curves = [("com", "CoM (ground projection)", "-", 1.6), ("cop", "CoP", "-", 0.7),
              ("cp", "capture point (leg odometry)", "--", 1.0)]
    # the estimator's filtered capture point, where it differs from the odometry's (walking: foot slip)
    if any(math.hypot(f[0] - c[0], f[1] - c[1]) > 1e-4 for f, c in zip(cs.get("cpf", []), cs["cp"])):
        curves.append(("cpf", "capture point (fused)", ":", 1.0))
    for key, label, style, width in curves:
        xs = [p[0] for p in cs[key][::k]]
        ys = [p[1] for p in cs[key][::k]]
        ax.plot(xs, ys, style, label=label, linewidth=width)
        ax.plot(xs[:1], ys[:1], "o", color=ax.lines[-1].get_color(), markersize=4)
    n = len(cs["poly"])
    picks = sorted({round(i * (n - 1) / max(1, POLYGON_SAMPLES - 1)) for i in range(POLYGON_SAMPLES)}) if n else []
    labelled = False
    for j, i in enumerate(picks):
        poly = cs["poly"][i]
        if len(poly) >= 2:   # empty while airborne / lying: nothing to draw
            shade = 0.25 + 0.75 * j / max(1, len(picks) - 1)   # later samples darker
            ax.add_patch(Polygon(poly, closed=True, fill=False, edgecolor=(0.2, 0.2, 0.2, shade),
                                 linewidth=0.8, label=None if labelled else "support polygon (sampled)"))
            labelled = True
    for ob in obstacles:
        color = "tab:red" if ob.is_target else "tab:gray"
        ax.add_patch(Polygon(_box_corners(ob), closed=True, alpha=0.35, color=color))
        ax.annotate(ob.name or ("target" if ob.is_target else "obstacle"),
                    (ob.pose.position.x, ob.pose.position.y), fontsize=8, ha="center")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("top view: CoM, CoP, capture point, support polygon, obstacles")
    ax.grid(True, linewidth=0.3)
    ax.legend(fontsize=8, loc="best")
    return _save(fig, path)


def plot_centroidal_time(cs: dict[str, list], path: pathlib.Path) -> pathlib.Path:
    fig, (a1, a2, a3) = _figure(rows=3, size=(8, 7))
    k = _stride(len(cs["t"]))
    t0 = cs["t"][0]
    t = [x - t0 for x in cs["t"][::k]]
    a1.plot(t, [math.degrees(x) for x in cs["lean"][::k]])
    a1.set_ylabel("lean angle (deg)")
    a2.plot(t, [p[2] for p in cs["com"][::k]])
    a2.set_ylabel("CoM height (m)")
    a3.plot(t, [math.hypot(*v) for v in cs["vel"][::k]], label="|v|")
    a3.plot(t, [math.hypot(v[0], v[1]) for v in cs["vel"][::k]], "--", label="horizontal")
    a3.set_ylabel("CoM speed (m/s)")
    a3.legend(fontsize=8)
    a3.set_xlabel(f"time since {t0:.3f} s (s)")
    for a in (a1, a2, a3):
        a.grid(True, linewidth=0.3)
    return _save(fig, path)


def plot_joint_positions(joints: dict[str, list[tuple[float, float]]], path: pathlib.Path) -> pathlib.Path:
    fig, (ax,) = _figure(size=(10, 6))
    t0 = min(s[0][0] for s in joints.values() if s)
    for name, series in joints.items():
        k = _stride(len(series))
        ax.plot([s[0] - t0 for s in series[::k]], [s[1] for s in series[::k]], linewidth=0.8, label=name)
    ax.set_xlabel(f"time since {t0:.3f} s (s)")
    ax.set_ylabel("position (rad or m)")
    ax.set_title("joint positions")
    ax.grid(True, linewidth=0.3)
    ax.legend(fontsize=6, ncol=2, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def plot_fall_geometry(result: dict, obstacles: list[Any], cs: dict[str, list], path: pathlib.Path) -> pathlib.Path:
    """Paper 1, Fig. 5 for one run: P, T, the landing CoM and the avoidance angle at P."""
    from matplotlib.patches import Arc, Polygon

    fig, (ax,) = _figure(size=(8, 7))
    for ob in obstacles:
        color = "tab:red" if ob.is_target else "tab:gray"
        ax.add_patch(Polygon(_box_corners(ob), closed=True, alpha=0.3, color=color))
    if cs["t"]:
        k = _stride(len(cs["t"]))
        ax.plot([p[0] for p in cs["com"][::k]], [p[1] for p in cs["com"][::k]], "-", color="tab:blue",
                linewidth=1.0, label="CoM (ground projection)")
    p = result["initial_cop"]
    land = result.get("landing_com")
    target = next(((ob.pose.position.x, ob.pose.position.y) for ob in obstacles if ob.is_target), None)
    ax.plot(*p, "ko", label="P: CoP when the push began")
    headings = []
    if land is not None:
        ax.annotate("", xy=land[:2], xytext=p, arrowprops={"arrowstyle": "->", "color": "tab:blue", "lw": 2})
        ax.plot(land[0], land[1], "s", color="tab:blue", label="CoM when the trunk landed")
        headings.append(math.degrees(math.atan2(land[1] - p[1], land[0] - p[0])))
    if target is not None:
        ax.annotate("", xy=target, xytext=p, arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5,
                                                         "linestyle": "--"})
        ax.plot(*target, "r*", markersize=12, label="T: target")
        headings.append(math.degrees(math.atan2(target[1] - p[1], target[0] - p[0])))
    alpha = result.get("avoidance_angle_deg")
    if len(headings) == 2 and alpha is not None:
        lo, hi = sorted(headings)
        if hi - lo > 180:
            lo, hi = hi, lo + 360
        ax.add_patch(Arc(p, 0.5, 0.5, theta1=lo, theta2=hi, color="k"))
        mid = math.radians((lo + hi) / 2)
        ax.annotate(f"avoidance angle {alpha:.0f} deg", (p[0] + 0.3 * math.cos(mid), p[1] + 0.3 * math.sin(mid)),
                    fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fell = "fell" if result.get("fell") else "did not fall"
    ax.set_title(f"fall geometry (paper 1, Fig. 5): {fell}, min target distance "
                 f"{result.get('min_target_distance_m')} m")
    ax.grid(True, linewidth=0.3)
    ax.legend(fontsize=8, loc="best")
    return _save(fig, path)


def plot_run(bag_path: str | os.PathLike, out_dir: str | os.PathLike) -> list[pathlib.Path]:
    """Write the plots a bag has data for into ``out_dir``; returns their paths (maybe empty)."""
    bag = resolve_bag(bag_path)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = load_series(bag)
    written: list[pathlib.Path] = []
    cs = data["centroidal"]
    if cs["t"]:
        written.append(plot_top_view(cs, data["obstacles"], out / "top_view.png"))
        written.append(plot_centroidal_time(cs, out / "centroidal_time.png"))
    if any(data["joints"].values()):
        written.append(plot_joint_positions(data["joints"], out / "joint_positions.png"))
    res = data["result"]
    if res and res.get("fell") and res.get("initial_cop"):
        written.append(plot_fall_geometry(res, data["obstacles"], cs, out / "fall_geometry.png"))
    return written


def plot_main(path: str | os.PathLike, out_dir: str | os.PathLike | None = None) -> int:
    """``humfall bag plot``: plots next to the bag (or into ``out_dir``). 0 ok, 1 nothing to plot/error."""
    try:
        bag = resolve_bag(path)
        written = plot_run(bag, out_dir if out_dir is not None else bag.parent)
    except (OSError, ValueError) as exc:
        print(f"humfall bag plot: {exc}", file=sys.stderr)
        return 1
    if not written:
        print(f"humfall bag plot: {bag} has no {CENTROIDAL_TOPIC} or {JOINT_STATES_TOPIC} messages",
              file=sys.stderr)
        return 1
    for p in written:
        print(p)
    return 0

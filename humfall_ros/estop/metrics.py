"""The ``estop`` section of result.json (issue 12) from a run's measurements and the plan. No rclpy."""
from __future__ import annotations

import math

import numpy as np

from humfall_ros.estop.frame import StopFrame
from humfall_ros.estop.planner import StopPlan
from humfall_ros.model.humanoid import point_in_polygon_margin


def estop_result(plan: StopPlan | None, t, com, cop, cop_margin, start_time: float, fell: bool,
                 settle_speed: float = 0.01, frame: StopFrame | None = None, polygon=None,
                 end_time: float | None = None, speed_window: float = 0.02) -> dict:
    """Summary of an executed stop, measured in the stop frame on the measured feet.

    Args:
        plan: the plan that ran (None: no stop was planned).
        t: sample times [s], (n,); com: measured CoM [m], (n, 3); cop: measured CoP [m], (n, 3).
        cop_margin: CoP distance inside the support polygon [m], (n,) (-inf: no contact).
        start_time: the stop's start [s] (after a single-support wait).
        fell: the run's fall verdict.
        settle_speed: CoG speed that counts as stopped [m/s].
        frame: the stop frame the figures are measured in: the plan's carried onto the measured feet at the start
            (``EstopStatus.feet_frame_origin`` / ``feet_major_axis``; ``EstopController.feet_frame``); None: the
            plan's own (the pattern's world; wrong by 0.1-0.2 m when the robot has yawed off its pattern).
        polygon: the stop's double-support polygon on the measured feet (k, 2) [m]
            (``EstopStatus.feet_support_polygon``): given, ``min_cop_margin_m`` is the CoP's distance inside it
            (ticks whose ``cop_margin`` is -inf, no contact, stay -inf); None: ``cop_margin`` as given.
        end_time: the stop's figures end here [s] (the feet step of the return home starts, §V step 3:
            ``EstopStatus.align_start_time``); None / NaN: the run's end.
        speed_window: the CoG speed is the CoG's displacement over this window [s] (centred) divided by its
            length: a central difference over two ticks reads a 40 um step of the leg odometry (a contact switch) as
            0.01 m/s, and one such step seconds after the stop had made ``stop_time_s`` 3.2 s where the
            estimated velocity and the ground truth give 1.25 s (1.8 km/h, ds_mid, session 17).
    Returns:
        ``feasible``, ``n3_m`` (Major), ``final_cog_major_m``, ``final_cog_minor_m`` (in the stop frame),
        ``max_cop_minor_m`` (largest |Minor| CoP displacement after the start), ``min_cop_margin_m``,
        ``stop_time_s`` (start to the CoG staying slower than ``settle_speed``; NaN if never), ``fell``.
    """
    if plan is None:
        return {"feasible": False, "n3_m": math.nan, "final_cog_major_m": math.nan, "final_cog_minor_m": math.nan,
                "max_cop_minor_m": math.nan, "min_cop_margin_m": math.nan, "stop_time_s": math.nan,
                "fell": bool(fell)}
    t = np.asarray(t, float)
    com = np.asarray(com, float)
    cop = np.asarray(cop, float)
    cop_margin = np.asarray(cop_margin, float)
    if end_time is not None and math.isfinite(end_time) and len(t):
        keep = t < end_time
        t, com, cop, cop_margin = t[keep], com[keep], cop[keep], cop_margin[keep]
    after = t >= start_time
    frame = plan.frame if frame is None else frame
    local_com = frame.to_local(com[:, :2])
    local_cop = frame.to_local(cop[after, :2])
    if polygon is not None and len(cop_margin):
        poly = np.asarray(polygon, float).reshape(-1, 2)
        cop_margin = np.array([-math.inf if (m == -math.inf or not np.isfinite(c[:2]).all())
                               else point_in_polygon_margin(np.array([c[0], c[1], 0.0]), poly)
                               for m, c in zip(cop_margin, cop)])
    speed = _windowed_speed(t, com[:, :2], speed_window)
    moving = np.nonzero(after & (speed >= settle_speed))[0]
    if len(moving) == 0:
        stop = 0.0
    elif moving[-1] + 1 < len(t):
        stop = float(t[moving[-1] + 1] - start_time)
    else:
        stop = math.nan
    return {"feasible": bool(plan.feasible), "n3_m": float(plan.major.n3),
            "final_cog_major_m": float(local_com[-1, 1]), "final_cog_minor_m": float(local_com[-1, 0]),
            "max_cop_minor_m": float(np.max(np.abs(local_cop[:, 0]))) if len(local_cop) else math.nan,
            "min_cop_margin_m": float(np.min(cop_margin[after])) if after.any() else math.nan,
            "stop_time_s": stop, "fell": bool(fell)}


def _windowed_speed(t: np.ndarray, xy: np.ndarray, window: float) -> np.ndarray:
    """|xy(t + w/2) - xy(t - w/2)| / (their time difference), the samples nearest inside the run (n,)."""
    if len(t) < 2:
        return np.zeros(len(t))
    lo = np.clip(np.searchsorted(t, t - 0.5 * window, side="left"), 0, len(t) - 1)
    hi = np.clip(np.searchsorted(t, t + 0.5 * window, side="right") - 1, 0, len(t) - 1)
    same = hi <= lo   # a window narrower than the sampling: the neighbouring samples
    lo = np.where(same, np.maximum(np.arange(len(t)) - 1, 0), lo)
    hi = np.where(same, np.minimum(np.arange(len(t)) + 1, len(t) - 1), hi)
    span = t[hi] - t[lo]
    return np.hypot(*(xy[hi] - xy[lo]).T) / np.where(span > 0, span, np.inf)


def estop_result_from_bag(bag, fell: bool, settle_speed: float = 0.01) -> dict:
    """The same section from a run's bag (what ``humfall up`` adds to result.json): the measured CoG / CoP
    and contact (no contact polygon: margin -inf) from ``/centroidal_state``; n3, feasibility, start and the stop
    frame and polygon on the measured feet (``feet_frame_origin``, ``feet_major_axis``, ``feet_support_polygon``)
    from the last ``/estop/status`` that started a stop (humfall_ros.estop.plots.run_from_bag); a bag without
    those fields (older message): the plan's frame and the measured support polygons. No stop: the empty
    section."""
    import types

    from humfall_ros.estop.plots import run_from_bag
    from humfall_ros.recording.reader import read_messages, resolve_bag

    try:
        run = run_from_bag(bag)
    except ValueError:
        return estop_result(None, [], [], [], [], math.nan, fell, settle_speed)
    feasible = False
    margins = {}
    feet = None
    align_start = math.nan
    for raw, m in read_messages(resolve_bag(bag), ["/estop/status", "/centroidal_state"]):
        k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if raw.topic == "/estop/status":
            if math.isfinite(m.start_time):
                feasible = bool(m.feasible)
                align_start = float(getattr(m, "align_start_time", math.nan))
                if hasattr(m, "feet_frame_origin") and math.isfinite(m.feet_frame_origin.x):
                    feet = (np.array([m.feet_frame_origin.x, m.feet_frame_origin.y]),
                            np.array([m.feet_major_axis.x, m.feet_major_axis.y]),
                            np.array([(p.x, p.y) for p in m.feet_support_polygon], float).reshape(-1, 2))
        else:
            poly = np.array([(q.x, q.y) for q in m.support_polygon], float).reshape(-1, 2)
            margins[k] = point_in_polygon_margin(np.array([m.cop.x, m.cop.y, 0.0]), poly) if len(poly) >= 3 \
                else -math.inf
    origin, major, polygon = (run.frame_origin, run.frame_major, None) if feet is None else feet
    major = major / np.linalg.norm(major)
    frame = StopFrame(origin, major, np.array([major[1], -major[0]]))
    plan = types.SimpleNamespace(frame=frame, feasible=feasible, major=types.SimpleNamespace(n3=run.n3))
    cop_margin = [margins.get(int(round(t * 1e9)), -math.inf) for t in run.t]
    return estop_result(plan, run.t, run.com, run.cop, cop_margin, run.start, fell, settle_speed,
                        polygon=polygon if polygon is not None and len(polygon) >= 3 else None, end_time=align_start)


__all__ = ["estop_result", "estop_result_from_bag"]

"""The ``estop`` section of result.json (issue 12) from a run's measurements and the plan. No rclpy."""
from __future__ import annotations

import math

import numpy as np

from humfall_ros.estop.planner import StopPlan


def estop_result(plan: StopPlan | None, t, com, cop, cop_margin, start_time: float, fell: bool,
                 settle_speed: float = 0.01) -> dict:
    """Summary of an executed stop.

    Args:
        plan: the plan that ran (None: no stop was planned).
        t: sample times [s], (n,); com: measured CoM [m], (n, 3); cop: measured CoP [m], (n, 3).
        cop_margin: CoP distance inside the support polygon [m], (n,) (-inf: no contact).
        start_time: the stop's start [s] (after a single-support wait).
        fell: the run's fall verdict.
        settle_speed: CoG speed that counts as stopped [m/s].
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
    after = t >= start_time
    local_com = plan.frame.to_local(com[:, :2])
    local_cop = plan.frame.to_local(cop[after, :2])
    dt = np.gradient(t)
    speed = np.hypot(*(np.gradient(com[:, :2], axis=0) / dt[:, None]).T)
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
            "min_cop_margin_m": float(np.min(np.asarray(cop_margin, float)[after])) if after.any() else math.nan,
            "stop_time_s": stop, "fell": bool(fell)}


def estop_result_from_bag(bag, fell: bool, settle_speed: float = 0.01) -> dict:
    """The same section from a run's bag (what ``humfall up`` can add to result.json): the measured CoG / CoP
    and polygon margins from ``/centroidal_state``, the plan's frame, n3, feasibility and start from the last
    ``/estop/status`` that started a stop (humfall_ros.estop.plots.run_from_bag). No stop: the empty section."""
    import types

    from humfall_ros.estop.frame import StopFrame
    from humfall_ros.estop.plots import run_from_bag
    from humfall_ros.model.humanoid import point_in_polygon_margin
    from humfall_ros.recording.reader import read_messages, resolve_bag

    try:
        run = run_from_bag(bag)
    except ValueError:
        return estop_result(None, [], [], [], [], math.nan, fell, settle_speed)
    feasible = False
    margins = {}
    for raw, m in read_messages(resolve_bag(bag), ["/estop/status", "/centroidal_state"]):
        k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if raw.topic == "/estop/status":
            if math.isfinite(m.start_time):
                feasible = bool(m.feasible)
        else:
            poly = np.array([(q.x, q.y) for q in m.support_polygon], float).reshape(-1, 2)
            margins[k] = point_in_polygon_margin(np.array([m.cop.x, m.cop.y, 0.0]), poly) if len(poly) >= 3 \
                else -math.inf
    major = run.frame_major / np.linalg.norm(run.frame_major)
    frame = StopFrame(run.frame_origin, major, np.array([major[1], -major[0]]))
    plan = types.SimpleNamespace(frame=frame, feasible=feasible, major=types.SimpleNamespace(n3=run.n3))
    cop_margin = [margins.get(int(round(t * 1e9)), -math.inf) for t in run.t]
    return estop_result(plan, run.t, run.com, run.cop, cop_margin, run.start, fell, settle_speed)


__all__ = ["estop_result", "estop_result_from_bag"]

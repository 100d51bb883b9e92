"""Client of the ``plan_fall`` service, behind ``humfall plan-fall``.

    humfall plan-fall --ke 30 [--wall 0.8] [--direction 1] [--mode LF/RF] [--budget S] [--profile execution]
                      [--json] [--plots DIR]

Prints a human summary, or with --json one JSON object (success, reason,
contact_sequence, node_ke, final_ke, nlp_times_s, total_time_s, landings (per
landing: limb, touchdown speeds, pre/post-impact KE, absorbed energy, impulse),
landings_within_limits, ...).
Exit code: 0 plan found, 1 no plan (service answered success=false),
2 service unavailable or no answer in time. ``--plots DIR`` also writes the
plan's contact transition tree, stick figures and kinetic energy over time
(paper 2, Fig. 1, 5-7) as PNG files into DIR.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

SERVICE = "plan_fall"


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="humfall plan-fall", description="Plan a multi-contact fall mitigation")
    ap.add_argument("--ke", type=float, required=True, help="initial kinetic energy (J)")
    ap.add_argument("--wall", type=float, default=0.0, help="wall at x = WALL m ahead of the stance (<= 0: none)")
    ap.add_argument("--direction", type=float, default=1.0, help="+1 forward push, -1 backward")
    ap.add_argument("--mode", default="LF/RF", help="initial contact mode, e.g. LF/RF")
    ap.add_argument("--budget", type=float, default=0.0, help="planning time budget (s); 0: node default")
    ap.add_argument("--profile", default="", help="planner_profile: '' (the node's parameters) or 'execution' "
                    "(a plan for the 3-D robot: multicontact.planner.FOR_EXECUTION and its library)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--plots", default="", help="write the tree, stick-figure and KE plots of the answer into DIR")
    ap.add_argument("--service", default=SERVICE, help="service name")
    ap.add_argument("--wait", type=float, default=10.0, help="seconds to wait for the service to appear")
    ap.add_argument("--timeout", type=float, default=0.0,
                    help="seconds to wait for the answer (default: budget + 30 s, or 630 s)")
    return ap.parse_args(argv)


def _nan_to_none(x):
    return None if isinstance(x, float) and not math.isfinite(x) else x


def response_to_dict(resp) -> dict:
    return {
        "success": bool(resp.success), "reason": resp.reason,
        "contact_sequence": list(resp.contact_sequence), "node_ke": [float(x) for x in resp.node_ke],
        "final_ke": _nan_to_none(float(resp.final_ke)), "nlp_times_s": [float(x) for x in resp.nlp_times_s],
        "total_time_s": float(resp.total_time_s), "nlp_count": int(resp.nlp_count),
        "tree_nodes": int(resp.tree_nodes), "deepest_depth": int(resp.deepest_depth),
        "segments": [{"kind": s.kind, "mode": s.mode, "target_mode": s.target_mode,
                      "duration_s": float(s.time[-1]) if len(s.time) else 0.0,
                      "ke_start": float(s.kinetic_energy[0]) if len(s.kinetic_energy) else None,
                      "ke_end": float(s.kinetic_energy[-1]) if len(s.kinetic_energy) else None}
                     for s in resp.segments],
        "landings": [{f: getattr(x, f) for f in ("limb", "surface", "time", "normal_speed", "tangential_speed",
                                                  "pre_impact_ke", "post_impact_ke", "absorbed_energy",
                                                  "normal_impulse", "tangential_impulse",
                                                  "impulse_friction_ratio", "within_limits",
                                                  "exceeded")} for x in resp.landings],
        "landings_within_limits": bool(resp.landings_within_limits),
        "transition_objective": resp.transition_objective,
    }


def summary(d: dict) -> str:
    from humfall_ros.multicontact.modes import strategy_of   # here: the client stays light to start

    lines = [("PLAN FOUND: " if d["success"] else "NO PLAN: ") + d["reason"]]
    if d["contact_sequence"]:
        seq = "  ->  ".join(f"{m} ({ke:.1f} J)" for m, ke in zip(d["contact_sequence"], d["node_ke"]))
        lines.append(f"contact sequence: {seq}  [{strategy_of(d['contact_sequence'])}]")
        lines.append(f"final kinetic energy: {d['final_ke']:.3g} J")
    for s in d["segments"]:
        tgt = f" -> {s['target_mode']}" if s["kind"] == "transition" else ""
        lines.append(f"  {s['kind']:<11} {s['mode']}{tgt}: {s['duration_s']:.2f} s, "
                     f"KE {s['ke_start']:.2f} -> {s['ke_end']:.3g} J")
    for x in d.get("landings", []):
        lines.append(f"  landing {x['limb']} on the {x['surface']} at {x['time']:.2f} s: touchdown "
                     f"{x['normal_speed']:.2f} m/s normal, {x['tangential_speed']:.2f} m/s tangential; KE "
                     f"{x['pre_impact_ke']:.1f} -> {x['post_impact_ke']:.1f} J "
                     f"(absorbed {x['absorbed_energy']:.1f} J), "
                     f"impulse {x['normal_impulse']:.1f} N s (|t|/n {x['impulse_friction_ratio']:.2f})"
                     + ("" if x["within_limits"] else f"  BEYOND LIMITS: {x['exceeded']}"))
    if d.get("transition_objective"):
        lines.append(f"transition objective: {d['transition_objective']}")
    times = d["nlp_times_s"]
    if times:
        med = sorted(times)[len(times) // 2]
        where = (f"tree of {d['tree_nodes']} nodes, depth {d['deepest_depth']}" if d["tree_nodes"]
                 else "no tree (re-solved from the library)")
        nlps = f"{d['nlp_count']} NLP" + ("" if d["nlp_count"] == 1 else "s")
        lines.append(f"{nlps} (median {med:.2f} s), {where}, total {d['total_time_s']:.1f} s")
    if d.get("plots"):
        lines.append("plots: " + ", ".join(d["plots"]))
    return "\n".join(lines)


def write_plots(resp, d: dict, args) -> list[str]:
    """The answer's figures (multicontact.plots.write_plan) into ``args.plots``."""
    from humfall_ros.multicontact import plots
    from humfall_ros.multicontact.model import load_model
    from humfall_ros.multicontact.modes import Environment

    result = {"tree": json.loads(resp.tree_json) if resp.tree_json else None,
              "segments": plots.segments_from_msgs(resp.segments), "success": d["success"],
              "contact_sequence": d["contact_sequence"],
              "initial_ke": d["node_ke"][0] if d["node_ke"] else float(args.ke),
              "wall_x": Environment.from_distance(args.wall).wall_x}   # the request's convention
    tag = f"plan_{args.ke:g}J" + (f"_wall{args.wall:g}" if args.wall > 0 else "")
    return plots.write_plan(load_model(), result, args.plots, tag)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    os.environ.setdefault("ROS_LOG_DIR", os.path.join(os.path.expanduser("~"), ".ros", "log"))
    import rclpy
    from humfall_interfaces.srv import PlanFall

    rclpy.init(args=None)
    node = rclpy.create_node("plan_fall_client")
    try:
        client = node.create_client(PlanFall, args.service)
        if not client.wait_for_service(timeout_sec=args.wait):
            msg = (f"service '{args.service}' not available after {args.wait:.0f} s: "
                   "is the multicontact_planner node running (humfall run multicontact_planner)?")
            if args.json:
                print(json.dumps({"success": False, "reason": msg}))
            else:
                print(msg, file=sys.stderr)
            return 2
        req = PlanFall.Request()
        req.kinetic_energy = float(args.ke)
        req.direction = float(args.direction)
        req.initial_mode = args.mode
        req.wall_distance = float(args.wall)
        req.time_budget = float(args.budget)
        req.planner_profile = args.profile
        timeout = args.timeout or ((args.budget + 30.0) if args.budget > 0 else 630.0)
        future = client.call_async(req)
        t0 = time.monotonic()
        while rclpy.ok() and not future.done() and time.monotonic() - t0 < timeout:
            rclpy.spin_until_future_complete(node, future, timeout_sec=0.5)
        if not future.done():
            msg = f"no answer from '{args.service}' within {timeout:.0f} s"
            print(json.dumps({"success": False, "reason": msg}) if args.json else msg,
                  file=sys.stdout if args.json else sys.stderr)
            return 2
        resp = future.result()
        d = response_to_dict(resp)
        if args.plots:
            d["plots"] = write_plots(resp, d, args)
        print(json.dumps(d) if args.json else summary(d))
        return 0 if d["success"] else 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())

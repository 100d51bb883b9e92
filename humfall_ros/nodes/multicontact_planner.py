"""multicontact_planner: the ``plan_fall`` service (paper 2, Algorithm 1).

Thin shell over humfall_ros.multicontact.planner. The service callback runs
in a reentrant callback group on a MultiThreadedExecutor, so a plan that takes
tens of seconds never blocks the executor (IPOPT runs with the GIL released).
One plan runs at a time; up to ``queue_size`` further requests wait their turn,
any more are answered at once with success=false and the reason.
"""
from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import rclpy.executors
from humfall_interfaces.msg import LandingReport, PlanSegment
from humfall_interfaces.srv import PlanFall
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from humfall_ros.multicontact import contacts as C
from humfall_ros.multicontact.modes import Environment, mode_label
from humfall_ros.multicontact.planner import PROFILES, FallPlanner
from humfall_ros.multicontact.resim import shutdown_check_pool
from humfall_ros.nodes.common import Params, leave_now, run_node

NAME = "multicontact_planner"


class MulticontactPlanner(Node):
    def __init__(self):
        super().__init__(NAME)
        p = Params(self)
        values = p.declare_all()   # every parameter of config/multicontact_planner.yaml
        self.queue_size = values["queue_size"]
        warm = values["warm_up"]
        try:
            self.planner = FallPlanner.from_params(values)   # keeps the values: a request's planner_profile
        except ValueError as e:   # a library file that cannot be used: say why and stop (exit 2)
            self.get_logger().fatal(str(e))
            raise SystemExit(2) from None
        self._state = threading.Lock()
        self._plan_lock = threading.Lock()
        self._pending = 0
        self._running_since: float | None = None
        self.group = ReentrantCallbackGroup()
        self.srv = self.create_service(PlanFall, "plan_fall", self.on_plan_fall, callback_group=self.group)
        self._closing = False
        if warm:
            threading.Thread(target=self._warm_up, name="nlp-warm-up", daemon=True).start()
        lib = self.planner.library
        opt_cfg, plan_cfg = self.planner.opt.cfg, self.planner.cfg
        self.get_logger().info(f"plan_fall ready (n={self.planner.model.n}, m={self.planner.model.m}, "
                               f"Nd={opt_cfg.n_knots}, objective={opt_cfg.transition_objective}, "
                               f"queue_size={self.queue_size}, library="
                               + (f"{plan_cfg.library_file}: {len(lib.entries)} plans" if lib else "none") + ")")

    def _warm_up(self):
        """Build the NLP structures of the root two-foot mode (the sweep's first
        level) and of the one-hand node below it (where the paper objective's plans
        go next: 20 J stops there, 30 J+ expands it) so that a request does not pay for them."""
        hand = ("LF", "RF", "LH")
        segments = [(("LF", "RF"), "", ""), (("LF", "RF"), "add", "LH"), (("LF", "RF"), "remove", "LF"),
                    (("RF",), "", ""), (("RF",), "add", "LF"),
                    (hand, "", ""), (hand, "add", "RH"), (hand, "remove", "LF"),
                    (hand, "remove", "RF")]   # (mode, change, extremity)
        t0 = time.perf_counter()
        for mode, change, ext in segments:
            if self._closing:
                return
            self.planner.opt.structures(mode, change, ext, Environment())   # NLP and seed projector
        self.get_logger().info(f"warm-up: {len(segments)} NLP structures built in {time.perf_counter() - t0:.1f} s")
        self._warm_library(self.planner, "the library")
        # then each request profile's planner and library (the execution profile's: ~20 s), so that the first
        # request of a profile is answered as fast as the later ones
        for name in PROFILES:
            if self._closing:
                return
            t0 = time.perf_counter()
            try:
                planner = self.planner.profile(name)
            except ValueError as e:   # its library cannot be used: its requests will say why
                self.get_logger().warning(f"warm-up: planner_profile {name!r} not usable: {e}")
                continue
            self.get_logger().info(f"warm-up: planner_profile {name!r} built in {time.perf_counter() - t0:.1f} s")
            self._warm_library(planner, f"the {name!r} profile's library")

    def _warm_library(self, planner: FallPlanner, label: str) -> None:
        """A library's re-plans made ready (``FallPlanner.warm_up_library``), logged."""
        if planner.library is None:
            return
        t0 = time.perf_counter()
        worker, n = planner.warm_up_library(stop=lambda: self._closing)
        self.get_logger().info(f"warm-up: {label}'s {n} segments ready in {time.perf_counter() - t0:.1f} s, its "
                               "re-plans checked " + ("in a worker process" if worker else "in process"))

    def close(self):
        self._closing = True

    # ------------------------------------------------------------ service
    def on_plan_fall(self, request: PlanFall.Request, response: PlanFall.Response):
        with self._state:
            if self._pending > self.queue_size:
                since = time.perf_counter() - (self._running_since or time.perf_counter())
                response.success = False
                response.reason = (f"busy: a plan has been running for {since:.1f} s and "
                                   f"{self._pending - 1} request(s) are queued (queue_size={self.queue_size}); "
                                   "retry later")
                return response
            self._pending += 1
        try:
            with self._plan_lock:
                self._running_since = time.perf_counter()
                req = {"q": list(request.q), "v": list(request.v), "kinetic_energy": request.kinetic_energy,
                       "direction": request.direction, "initial_mode": request.initial_mode,
                       "wall_distance": request.wall_distance, "time_budget": request.time_budget,
                       "planner_profile": request.planner_profile}
                try:
                    result = self.planner.plan(req)
                except Exception as e:  # noqa: BLE001 - the node must keep serving
                    self.get_logger().error(f"planner failed: {e!r}")
                    result = {"success": False, "reason": f"internal error: {e}", "segments": []}
                self._fill(response, result)
                profile = f"profile={request.planner_profile} " if request.planner_profile else ""
                self.get_logger().info(f"plan_fall: success={response.success} {profile}"
                                       f"source={result.get('source', '')} "
                                       f"sequence={list(response.contact_sequence)} "
                                       f"nlps={response.nlp_count} t={response.total_time_s:.1f}s: {response.reason}")
                if result.get("library_attempt"):   # why the library's answer was not used (each entry tried)
                    self.get_logger().info(f"plan_fall: the library first: {result['library_attempt']}")
        finally:
            with self._state:
                self._pending -= 1
        return response

    def _fill(self, resp: PlanFall.Response, r: dict):
        model = self.planner.model
        resp.success = bool(r.get("success", False))
        resp.reason = str(r.get("reason", ""))
        resp.contact_sequence = list(r.get("contact_sequence", []))
        resp.node_ke = [float(x) for x in r.get("node_ke", [])]
        fk = r.get("final_ke", float("nan"))
        resp.final_ke = float(fk) if fk is not None else math.nan
        resp.nlp_times_s = [float(x) for x in r.get("nlp_times_s", [])]
        resp.total_time_s = float(r.get("total_time_s", 0.0))
        resp.nlp_count = int(r.get("nlp_count", 0))
        resp.tree_nodes = int(r.get("tree_nodes", 0))
        resp.deepest_depth = int(r.get("deepest_depth", 0))
        resp.tree_json = json.dumps(r["tree"]) if r.get("tree") is not None else ""
        segs = []
        for s in r.get("segments", []):
            m = PlanSegment()
            m.kind = s.kind
            m.mode = mode_label(s.mode)
            m.target_mode = mode_label(s.target_mode)
            m.coordinate_names = list(model.coordinate_names)
            m.actuated_names = list(model.joint_names)
            m.time = s.time.tolist()
            m.q = s.q.ravel().tolist()
            m.v = s.v.ravel().tolist()
            m.u = s.u.ravel().tolist()
            m.contact_force = np.asarray(C.forces_per_point(s.rows, s.lam)).ravel().tolist()
            m.kinetic_energy = s.ke.tolist()
            segs.append(m)
        resp.segments = segs
        resp.landings = [landing_msg(x) for x in r.get("landings", [])]
        resp.landings_within_limits = bool(r.get("landings_within_limits", False))
        resp.transition_objective = self.planner.opt.cfg.transition_objective


def landing_msg(rep) -> LandingReport:
    """humfall_interfaces/LandingReport from a multicontact.landing.LandingReport."""
    m = LandingReport()
    for f in ("limb", "surface", "exceeded"):
        setattr(m, f, str(getattr(rep, f)))
    for f in ("time", "normal_speed", "tangential_speed", "pre_impact_ke", "post_impact_ke", "absorbed_energy",
              "normal_impulse", "tangential_impulse", "impulse_friction_ratio"):
        setattr(m, f, float(getattr(rep, f)))
    m.within_limits = bool(rep.within_limits)
    return m


def main(args=None) -> int:
    code = run_node(MulticontactPlanner, args=args, use_sim_time=False,
                    executor_factory=lambda: rclpy.executors.MultiThreadedExecutor(num_threads=4))
    shutdown_check_pool()   # the library check's worker process (leave_now skips the exit handlers)
    # rclpy is shut down and the node holds no files; what is left is the interpreter freeing the
    # warm-up's casadi NLP structures, measured at 1.65 s of the 1.7 s a SIGINT took with 9 of
    # them (the 2 s stop goal of issue 9), so leave without it
    leave_now(code)


if __name__ == "__main__":
    raise SystemExit(main())

"""A scenario put into a SimWorld, and its ground-truth fall metrics tracked tick by tick.

One place for both the ROS bridge and the in-process closed loop: obstacles and
timed pushes from the scenario, the target, and FallMetrics fed from the
simulator (the reference CoP P is taken when the first push begins).
"""
from __future__ import annotations

import numpy as np

from humfall_ros.scenario import push_time
from humfall_ros.sim.metrics import FallMetrics, foot_state
from humfall_ros.sim.world import Box, SimWorld


class GroundTruth:
    def __init__(self, world: SimWorld, sc: dict):
        """Set up ``world`` from a validated scenario dict (humfall_ros.scenario)."""
        self.world = world
        boxes = [Box(o["name"], tuple(o["position"]), tuple(o["size"]), o["yaw"], o["is_target"])
                 for o in sc["obstacles"]]
        world.set_obstacles(boxes)
        self.push_times = [push_time(sc, p) for p in sc["push"]]
        for p, t in zip(sc["push"], self.push_times):
            world.add_push(p["force"], p["point"], p["duration"], p["link"], start=t)
        self.metrics = FallMetrics()
        self.set_target(boxes)
        self.first_push_time = min(self.push_times, default=0.0)

    def set_target(self, boxes: list[Box]) -> None:
        """The box to avoid (T of paper 1, Fig. 5), after obstacles change."""
        self.target = next((b for b in boxes if b.is_target), None)
        self.metrics.target_xy = None if self.target is None else np.array(self.target.position[:2])

    def track(self) -> None:
        """Feed the metrics with the world's state after a control tick."""
        w = self.world
        if self.metrics.initial_cop is None and w.time >= self.first_push_time - 1e-9:
            self.metrics.set_reference_cop(w.ground_truth_cop())
        q = w.pinocchio_configuration()
        dist = w.distance_to(self.target.name) if self.target is not None else None
        self.metrics.update(w.time, w.model.com(q), w.trunk_tilt(), w.base_state()[0][2], dist,
                            w.non_foot_contact())
        # touchdowns and the CoP after them (alpha2); poses and CoP only computed on the ticks that use them
        self.metrics.update_feet(w.time, *foot_state(w, lazy=True))

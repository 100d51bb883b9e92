"""The fall trigger boundary (FTB, paper 1 §II-B) over features of the centroidal state.

Features (per control tick, from ``CentroidalObservation`` alone):

* for every edge of the support polygon, the 2-D pendulum of the CoM about it
  (``dynamics.toppling.edge_pendulum``): lean theta, rate theta', energy ratio
  e = E / E_crest and the signed separatrix margin (> 0: the pendulum falls over that
  edge; ``toppling.separatrix_margin``); the **leading edge** is the one with the largest
  margin, a **leading corner** when the CoM's projection lies beyond that edge's ends;
* the lean angle of P->G and the capture point's signed distance to the polygon
  (reported only: both cross their textbook limits in pushes this robot survives,
  see DESIGN.md "Measured facts for the controllers").

Trigger modes (``FtbConfig.mode``):

* ``ftb`` (ours): outside the boundary when the leading edge's separatrix margin exceeds
  ``margin_threshold`` for ``debounce_ms`` (the energy over the leading edge separates
  falls from recoveries), or the lean exceeds the ``lean_backstop_deg`` backstop;
* ``fixed`` (paper 1 §V-A): the fall starts ``fixed_delay_s`` after the push ends; the
  push end time is an input (``observation.inputs["push_end_time"]`` [s]).

While walking (``observation.inputs["walking/state"]`` with ``walking`` true, see
:class:`GaitReference`), the capture point leaves the stance foot in every normal step, so
the boundary is referenced to the gait: outside when the measured capture point is more than
``walking_capture_point_error`` from the gait's reference capture point (debounced), or when
the energy margin is positive over an edge of the *reference* support (the hook; walking is
being built, the reference fields are the contract).

The state machine is data (:data:`TRANSITIONS`): BALANCED -> FALLING (the trigger, with
the :class:`FallEvent` published once, on the edge) -> FALLEN (lean beyond
``fallen_lean_deg`` or ``falling_timeout_s`` in FALLING, or the CoM below
``fallen_com_height_fraction`` of its first height). FALLING and FALLEN go back to BALANCED
when the robot has **recovered** (inside the boundary, still, upright for ``recover_s``: a step
captured the fall; FALLEN is reached that way too, by ``falling_timeout_s`` while a captured robot
rocks to a stand) or through :meth:`FtbMonitor.reset` (``ftb/reset``, sim time going back).
Either **clears** the fall event: ``FtbStatus.fall_event`` is None again, ``FtbStatus.cleared``
carries the cleared event on that tick (the node publishes it on ``fall_event`` with
``cleared = true``), and the monitor's ``latched`` maps ``fall_event`` to None (the in-process
loop then drops that input, as a node drops a cleared latched event). A later trigger is a new event.
"""
from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any, Protocol, runtime_checkable

import numpy as np

from humfall_ros import params
from humfall_ros.control.contract import CentroidalObservation, Observation
from humfall_ros.dynamics.pendulum import GRAVITY
from humfall_ros.dynamics.toppling import FallOutcome, edge_pendulum, time_to_lean
from humfall_ros.fall.geometry import PolygonEdges, polygon_margin_xy


class FtbState(enum.Enum):
    BALANCED = "balanced"
    FALLING = "falling"
    FALLEN = "fallen"


class TriggerMode(enum.Enum):
    FTB = "ftb"
    FIXED = "fixed"


@dataclasses.dataclass(frozen=True)
class Transition:
    """One row of the FTB state machine: ``source`` -> ``target`` when ``condition`` holds."""

    source: FtbState
    target: FtbState
    condition: str
    description: str


TRANSITIONS: tuple[Transition, ...] = (
    Transition(FtbState.BALANCED, FtbState.FALLING, "outside_boundary",
               "trigger condition of the mode held for debounce_ms (ftb) / push end + fixed_delay_s (fixed)"),
    Transition(FtbState.BALANCED, FtbState.FALLEN, "fallen", "lean beyond fallen_lean_deg without a trigger"),
    Transition(FtbState.FALLING, FtbState.FALLEN, "fallen", "lean beyond fallen_lean_deg"),
    Transition(FtbState.FALLING, FtbState.FALLEN, "falling_timeout", "falling_timeout_s spent in FALLING"),
    Transition(FtbState.FALLING, FtbState.BALANCED, "recovered",
               "inside the boundary, lean below recover_lean_deg, CoM slower than recover_speed and above "
               "recover_com_height_fraction of its first height for recover_s (a step captured the fall); the "
               "fall event is cleared"),
    Transition(FtbState.FALLEN, FtbState.BALANCED, "recovered",
               "as from falling (fallen by falling_timeout_s while a captured robot rocked to a stand); cleared"),
    Transition(FtbState.FALLING, FtbState.BALANCED, "reset", "ftb/reset or sim time went back; cleared"),
    Transition(FtbState.FALLEN, FtbState.BALANCED, "reset", "ftb/reset or sim time went back; cleared"),
)


@dataclasses.dataclass(frozen=True)
class FtbConfig:
    """FTB parameters (declared in ``config/ftb_monitor.yaml``; units in the names)."""

    mode: TriggerMode = TriggerMode.FTB
    margin_threshold: float = 0.0
    debounce_ms: float = 10.0
    lean_backstop_deg: float = 25.0
    fallen_lean_deg: float = 60.0
    fallen_com_height_fraction: float = 0.5
    falling_timeout_s: float = 3.0
    fixed_delay_s: float = 0.05
    theta_threshold_deg: float = 15.0
    min_normal_force_fraction: float = 0.3
    walking_capture_point_error: float = 0.08
    walking_lean_backstop_deg: float = 40.0
    robot_weight: float = 0.0   # [N]; 0: taken as the first observations' normal force
    push_end_time_s: float = -1.0  # [s] fixed mode without a push_end_time input (< 0: unknown)
    use_walking_state: bool = False  # the node's tick also waits for walking/state (the gait reference)
    use_estop_status: bool = False  # ... and for estop/status (the stop's reference while it plays)
    recover_s: float = 0.5
    recover_speed: float = 0.05
    recover_lean_deg: float = 10.0
    recover_com_height_fraction: float = 0.9
    recover_from_fallen: bool = True

    @classmethod
    def from_params(cls, d: dict[str, Any]) -> FtbConfig:
        """From ``params.defaults("ftb_monitor")``-shaped dict; unknown keys are refused."""
        kw = dict(d)
        if "mode" in kw:
            kw["mode"] = TriggerMode(kw["mode"])
        return params.config_from(cls, kw, "ftb_monitor")


@runtime_checkable
class GaitReference(Protocol):
    """What the FTB reads from ``walking/state`` (the walking engineer's message, as a dataclass).

    Attributes:
        walking: a gait is running (False: standing, the plain boundary applies).
        support: "double", "left" or "right".
        reference_capture_point: the gait's capture point at this tick [m], (3,).
        reference_support_polygon: the support the gait plans for this tick [m], (k, 2).
    """

    walking: bool
    support: str
    reference_capture_point: np.ndarray
    reference_support_polygon: np.ndarray


@dataclasses.dataclass(frozen=True)
class GaitRef:
    """A :class:`GaitReference` (what :func:`gait_reference` makes of ``walking/state``)."""

    walking: bool
    support: str
    reference_capture_point: np.ndarray
    reference_support_polygon: np.ndarray
    stamp_ns: int = 0
    reference_feet_center: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))


def _xy(foot) -> tuple[float, float]:
    """(x, y) of a reference sole: a (x, y, z, yaw) tuple or a geometry_msgs/Pose [m]."""
    if foot is None:
        return math.nan, math.nan
    if hasattr(foot, "position"):
        return float(foot.position.x), float(foot.position.y)
    f = np.asarray(foot, float).reshape(-1)
    return (float(f[0]), float(f[1])) if f.size >= 2 else (math.nan, math.nan)


SUPPORT_NAMES = {"double": "double", "single_left": "left", "single_right": "right", "left": "left",
                 "right": "right", 0: "double", 1: "left", 2: "right"}


def gait_reference(x) -> GaitReference | None:
    """``walking/state`` as a :class:`GaitReference` (None: no gait input).

    Takes the walking controller's ``WalkingState`` (``walking``, ``released``, ``support`` "double" /
    "single_left" / "single_right", ``capture_point_ref``), its ROS message (the same fields), or a
    :class:`GaitReference` as it is. Released (fall event, e-stop) counts as not walking.
    """
    if x is None:
        return None
    if isinstance(x, GaitReference):
        return x
    cp = getattr(x, "capture_point_ref", None)
    if cp is None:
        return None
    if not isinstance(cp, np.ndarray) and hasattr(cp, "x"):
        cp = (cp.x, cp.y, cp.z)
    stamp = getattr(x, "stamp_ns", None)
    if stamp is None and hasattr(x, "header"):
        stamp = int(x.header.stamp.sec) * 1_000_000_000 + int(x.header.stamp.nanosec)
    support = getattr(x, "support", "double")
    (lx, ly), (rx, ry) = _xy(getattr(x, "left_foot", None)), _xy(getattr(x, "right_foot", None))
    return GaitRef(bool(getattr(x, "walking", False)) and not bool(getattr(x, "released", False)),
                   SUPPORT_NAMES.get(support, "double"), np.asarray(cp, float).reshape(-1)[:3].copy(),
                   np.zeros((0, 2)), int(stamp or 0), np.array([0.5 * (lx + rx), 0.5 * (ly + ry)]))


def stop_reference(estop_status, reference_feet_center=None) -> GaitRef | None:
    """The e-stop's plan as the motion reference while it plays (None otherwise).

    ``estop_status``: the e-stop's ``EstopStatus`` (or its message): ``active``, ``state``, ``omega_c`` and
    this tick's ``com_ref`` / ``com_velocity_ref`` (paper 3's generated CoG, world). The reference capture
    point is com_ref + com_velocity_ref / omega_c (the LIPM's, at the trigger height); the reference feet
    (``reference_feet_center``, [m] (2,)) are walking's planned soles of its last walking tick (the feet do
    not move during a stop; a released walking/state no longer carries them), so the error is taken
    relative to the feet like walking's (NaN / None: absolute). Why:
    a stopping robot still moves at walking speed over its front foot, and the standing boundary (energy
    over the leading edge) fired 12 ms into an unpushed 1.0 km/h stop (safe fall then took over).
    """
    if estop_status is None:
        return None
    if not bool(getattr(estop_status, "active", False)) or str(getattr(estop_status, "state", "")) != "stopping":
        return None

    def v3(x):
        if x is None:
            return np.full(3, np.nan)
        if hasattr(x, "x"):
            return np.array([x.x, x.y, x.z], float)
        return np.asarray(x, float).reshape(-1)[:3]

    c, cd = v3(getattr(estop_status, "com_ref", None)), v3(getattr(estop_status, "com_velocity_ref", None))
    w = float(getattr(estop_status, "omega_c", math.nan))
    if not (np.all(np.isfinite(c[:2])) and np.all(np.isfinite(cd[:2])) and math.isfinite(w) and w > 0):
        return None
    cp = np.array([c[0] + cd[0] / w, c[1] + cd[1] / w, 0.0])
    feet = np.full(2, np.nan) if reference_feet_center is None else np.asarray(reference_feet_center, float)[:2]
    return GaitRef(True, "double", cp, np.zeros((0, 2)), int(getattr(estop_status, "stamp_ns", 0) or 0),
                   feet.copy())


def capture_point_error(capture_point, feet_center, gait: GaitReference) -> float:
    """|Q - Q_ref| with both taken from their feet: (Q - feet centre) - (Q_ref - the gait's feet centre) [m].

    The gait's reference feet are the soles' planned poses, the measured ones the ankles' mid-point
    (the same point in x, y for a flat sole under its ankle). Relative to the feet, not absolute:
    measured on walking.yaml at 1.0 km/h, the feet land up to 6 cm to the side of the plan after 20 steps
    (the pattern does not re-plan from the measured feet), and the absolute error grows with them to 7.7 cm,
    while the error relative to the feet stays below 3 cm. Without reference feet (NaN): absolute.
    """
    q = np.asarray(capture_point, float)[:2]
    qr = np.asarray(gait.reference_capture_point, float)[:2]
    fr = np.asarray(getattr(gait, "reference_feet_center", (math.nan, math.nan)), float)[:2]
    if np.all(np.isfinite(fr)):
        fc = np.asarray(feet_center, float)[:2]
        return float(np.hypot(*((q - fc) - (qr - fr))))
    return float(np.hypot(*(q - qr)))


@dataclasses.dataclass
class FtbFeatures:
    """The FTB's feature vector of one tick.

    Attributes:
        energy_ratio: e over the leading edge [-] (1 = crest).
        separatrix_margin: signed |e - 1| over the leading edge, > 0 falls [-].
        theta, theta_dot: edge-pendulum lean [rad] and rate [rad/s] about the leading edge.
        pendulum_length: leading-edge pivot to CoM [m].
        lean_angle: P->G lean [rad] (reported).
        capture_point_margin: signed distance of Q to the polygon, > 0 inside [m] (reported).
        capture_point_error: |Q - Q_ref| while walking [m] (NaN standing).
        edge_start, edge_end: the leading edge [m], (2,) each (equal for a corner).
        edge_normal: its outward normal [-], (2,).
        on_corner: the CoM projects beyond the leading edge's ends (or a one-point polygon).
        valid: enough normal force and a non-empty polygon for the features to mean anything.
    """

    energy_ratio: float = math.nan
    separatrix_margin: float = math.nan
    theta: float = math.nan
    theta_dot: float = math.nan
    pendulum_length: float = math.nan
    lean_angle: float = math.nan
    capture_point_margin: float = math.nan
    capture_point_error: float = math.nan
    edge_start: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    edge_end: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    edge_normal: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    on_corner: bool = False
    valid: bool = False


@dataclasses.dataclass
class FallEvent:
    """Published once when the state leaves the FTB (the latched ``fall_event``).

    Attributes:
        stamp_ns: tick of the trigger [ns].
        trigger_mode: "ftb" or "fixed".
        reason: which condition fired.
        leading_edge_start, leading_edge_end: the leading edge [m], (3,), z = 0 (equal: a corner).
        leading_corner: the robot topples about a corner.
        cop: CoP P [m], (3,).
        reference_point: Q, the capture point (eq. 1-2) [m], (3,).
        fall_direction: heading of the leading edge's outward normal [rad].
        control_duration: time to ``theta_threshold`` by the edge pendulum [s] (inf: never, by the model).
        theta_threshold: the lean that ends the control duration [rad].
        energy_ratio: e over the leading edge at the trigger [-].
        separatrix_margin: its signed margin [-].
        lean_angle: P->G lean [rad].
        com, com_velocity: G [m] and dG/dt [m/s], (3,).
        support_polygon: the polygon at the trigger [m], (k, 2).
        walking: the boundary was referenced to the gait.
    """

    stamp_ns: int
    trigger_mode: str
    reason: str
    leading_edge_start: np.ndarray
    leading_edge_end: np.ndarray
    leading_corner: bool
    cop: np.ndarray
    reference_point: np.ndarray
    fall_direction: float
    control_duration: float
    theta_threshold: float
    energy_ratio: float
    separatrix_margin: float
    lean_angle: float
    com: np.ndarray
    com_velocity: np.ndarray
    support_polygon: np.ndarray
    walking: bool = False

    @property
    def time(self) -> float:
        return self.stamp_ns * 1e-9


@dataclasses.dataclass
class FtbStatus:
    """``ftb/status`` of one tick: the state, the features, and the fall event.

    Attributes:
        event: the fall event on the tick it fires (the edge), else None.
        fall_event: the latched event on every tick from the trigger on (until it is cleared: the
            ``recovered`` transition or ``reset``): a per-tick consumer acts on the status of tick k,
            never on when ``fall_event`` arrives.
        cleared: the event cleared on this tick (the recovery's edge), else None.
    """

    stamp_ns: int
    state: FtbState
    mode: str
    features: FtbFeatures
    time_in_state: float
    reason: str = ""
    event: FallEvent | None = None
    fall_event: FallEvent | None = None
    cleared: FallEvent | None = None


def polygon_width(poly) -> float:
    """Smallest extent of a convex polygon across any of its edges [m] (0 for a segment)."""
    p = np.asarray(poly, float).reshape(-1, 2)
    if len(p) < 3:
        return 0.0
    return _width(p.tolist(), _edges(p.tolist())[2])


def _edges(pts: list) -> tuple[list, list, list]:
    """``geometry.polygon_edges`` on Python floats (k <= 8 points every tick): (starts, ends, outward normals)."""
    k = len(pts)
    if k == 1:
        return [pts[0]], [pts[0]], [(math.nan, math.nan)]
    if k == 2:
        a, b = [pts[0], pts[1]], [pts[1], pts[0]]
    else:
        a, b = pts, pts[1:] + pts[:1]
    n = []
    for (ax, ay), (bx, by) in zip(a, b):
        ex, ey = bx - ax, by - ay
        length = max(math.sqrt(ex * ex + ey * ey), 1e-12)
        n.append((ey / length, -ex / length))
    return a, b, n


def _width(pts: list, normals: list) -> float:
    w = math.inf
    for (nx, ny), (ax, ay) in zip(normals, pts):
        na = nx * ax + ny * ay
        w = min(w, -min(nx * px + ny * py - na for px, py in pts))
    return w


def _strip_edge(poly, feet_center, qxy) -> PolygonEdges:
    """A thin polygon (the feet rocking on one line of corners) as one pivot line.

    The outward side is the one away from the ankles' mid-point (the rest of the soles is
    behind the line: the robot rocks back onto it rather than toppling that way); when the
    mid-point is on the line, the side the capture point is on.
    """
    c = poly.mean(axis=0)
    _u, _, vt = np.linalg.svd(poly - c)
    axis = vt[0]
    t = (poly - c) @ axis
    a, b = poly[int(np.argmin(t))], poly[int(np.argmax(t))]
    n = np.array([-axis[1], axis[0]])
    side = float((c - feet_center) @ n)
    if abs(side) < 0.01:
        side = float((qxy - c) @ n)
    if side < 0:
        n = -n
    return PolygonEdges(a[None], b[None], n[None])


def features_of(s: CentroidalObservation, polygon=None, g: float = GRAVITY,
                thin_width: float = 0.02, inner_edge_tolerance: float = 0.01) -> FtbFeatures:
    """The FTB features of one centroidal state.

    Args:
        s: the centroidal state.
        polygon: the support to topple about [m], (k, 2), CCW; default ``s.support_polygon``
            (the touching corners). The loaded soles' hull is the better choice when known.

    The leading edge is the edge the capture point lies furthest beyond (largest
    (Q - a) . n): with the touching corners only, a foot rocking on its toes gives a strip a
    few mm deep whose back edge has the CoM "beyond" it, and choosing by the largest margin
    would pick that back edge (measured: it fires at 250 N). The pendulum is then taken
    about the leading edge alone. A polygon thinner than ``thin_width`` [m] (the feet on
    their toe corners: three or four nearly collinear points) is one pivot line whose
    outward side is away from ``s.feet_center`` (:func:`_strip_edge`). Edges with the ankles'
    mid-point more than ``inner_edge_tolerance`` [m] beyond them (one foot's inner edge while
    the other is unloaded) are not leading-edge candidates.

    Every message runs this on <= 8 points: on Python floats, not numpy arrays (whose per-call
    overhead was 0.2 ms of the 0.23 ms a message cost); the strip's axis stays numpy's SVD.
    """
    poly = np.asarray(s.support_polygon if polygon is None else polygon, float).reshape(-1, 2)
    f = FtbFeatures(lean_angle=float(s.lean_angle))
    pts = poly.tolist()
    com = np.asarray(s.com, float).tolist()
    vel = np.asarray(s.com_velocity, float).tolist()
    cp = np.asarray(s.capture_point, float).tolist()
    if not pts or not all(math.isfinite(x) for x in (*com, *vel, *cp)) or \
            not all(math.isfinite(x) for p in pts for x in p):
        return f
    qx, qy = cp[0], cp[1]
    f.capture_point_margin = polygon_margin_xy(qx, qy, pts)
    fcx, fcy = np.asarray(s.feet_center, float).tolist()[:2]
    starts, ends, normals = _edges(pts)
    if len(pts) >= 3 and _width(pts, normals) < thin_width or len(pts) == 2 and thin_width > 0.0:
        e = _strip_edge(poly, np.array([fcx, fcy]), np.array([qx, qy]))
        starts, ends, normals = e.start.tolist(), e.end.tolist(), e.normal.tolist()
    if len(pts) == 1:  # one corner: the robot topples away from the rest of its soles (the ankles)
        ox, oy = pts[0][0] - fcx, pts[0][1] - fcy
        if math.hypot(ox, oy) < 0.01:
            ox, oy = qx - pts[0][0], qy - pts[0][1]
        norm = max(math.hypot(ox, oy), 1e-12)
        normal = (ox / norm, oy / norm)
        i = 0
    else:
        beyond = [(qx - ax) * nx + (qy - ay) * ny for (ax, ay), (nx, ny) in zip(starts, normals)]
        # an edge with the ankles' mid-point beyond it is the inner edge of one loaded foot: the
        # other foot is right there, so the CoM "beyond" it rocks back onto that foot (measured:
        # 0.9x pushes at 30-150 deg fired on it)
        inner = [(fcx - ax) * nx + (fcy - ay) * ny > inner_edge_tolerance
                 for (ax, ay), (nx, ny) in zip(starts, normals)]
        if not all(inner):
            beyond = [-math.inf if x else b for b, x in zip(beyond, inner)]
        i = max(range(len(beyond)), key=beyond.__getitem__)
        normal = normals[i]
    ax, ay = starts[i]
    relx, rely = com[0] - ax, com[1] - ay
    d = relx * normal[0] + rely * normal[1]
    h = com[2]
    length = math.hypot(d, h)
    theta = math.atan2(d, h)
    theta_dot = ((normal[0] * vel[0] + normal[1] * vel[1]) * h - vel[2] * d) / (length * length)
    e = length * theta_dot ** 2 / (2.0 * g) + math.cos(theta)   # toppling.energy_ratio, point mass
    falls = (e > 1.0 and theta_dot > 0.0) or (e < 1.0 and theta > 0.0) or (theta > 0.0 and theta_dot >= 0.0)
    f.energy_ratio, f.separatrix_margin = e, (1.0 if falls else -1.0) * abs(e - 1.0)   # toppling.separatrix_margin
    f.theta, f.theta_dot, f.pendulum_length = theta, theta_dot, length
    bx, by = ends[i]
    evx, evy = bx - ax, by - ay
    t = (relx * evx + rely * evy) / max(evx * evx + evy * evy, 1e-18) if len(pts) > 1 else 0.0
    if len(pts) == 1 or t <= 0.0 or t >= 1.0:
        corner = np.array((ax, ay) if t <= 0.5 else (bx, by))
        f.edge_start, f.edge_end = corner, corner.copy()
        f.on_corner = True
    else:
        f.edge_start, f.edge_end = np.array((ax, ay)), np.array((bx, by))
    f.edge_normal = np.array(normal, float)
    f.valid = True
    return f


class FtbMonitor:
    """The FTB state machine (see the module docstring); ``step`` once per control tick.

    A monitor of ``sim.closed_loop.ClosedLoop``: its value is ``ftb/status`` and it latches
    ``fall_event`` (as the node's transient-local topic) from the trigger on.
    """

    name = "ftb/status"

    def __init__(self, config: FtbConfig | None = None):
        self.config = config or FtbConfig()
        self.reset()

    @property
    def latched(self) -> dict[str, FallEvent | None]:
        """``{"fall_event": event}`` once it fired (the transient-local topic's last message);
        ``{"fall_event": None}`` once it was cleared (recovered or reset: the topic's "cleared" message),
        ``{}`` before any event."""
        if self.event is not None:
            return {"fall_event": self.event}
        return {"fall_event": None} if self.had_event else {}

    def reset(self) -> None:
        """Back to BALANCED, timers and the latched event cleared (``ftb/reset``)."""
        self.had_event = getattr(self, "had_event", False) or getattr(self, "event", None) is not None
        self.cleared_event: FallEvent | None = getattr(self, "event", None) or getattr(self, "cleared_event", None)
        self.state = FtbState.BALANCED
        self.state_since: float | None = None
        self.outside_since: float | None = None
        self.last_stamp: int | None = None
        self.event: FallEvent | None = None
        self.inside_since: float | None = None
        self.weight = self.config.robot_weight if self.config.robot_weight > 0 else None
        self.com_height: float | None = None
        self.gait_feet: np.ndarray | None = None  # walking's reference feet centre of its last walking tick

    # ---------------------------------------------------------------- conditions
    def _outside(self, obs: Observation, f: FtbFeatures) -> str:
        """The reason the state is outside the boundary this tick ("" inside)."""
        c = self.config
        t = obs.time
        if c.mode is TriggerMode.FIXED:
            end = obs.inputs.get("push_end_time")
            if end is None and c.push_end_time_s >= 0:
                end = c.push_end_time_s
            if end is not None and math.isfinite(float(end)) and t >= float(end) + c.fixed_delay_s - 1e-9:
                return f"fixed: {c.fixed_delay_s:.3f} s after the push ended at {float(end):.3f} s"
            return ""
        if not f.valid:
            return ""
        gait = gait_reference(obs.inputs.get("walking/state"))
        if gait is not None and gait.walking:
            self.gait_feet = np.asarray(getattr(gait, "reference_feet_center", (math.nan, math.nan)), float)[:2]
        else:  # an e-stop playing its plan is the motion reference then (on walking's last feet)
            gait = stop_reference(obs.inputs.get("estop/status"), self.gait_feet) or gait
        walking = gait is not None and gait.walking
        backstop = c.walking_lean_backstop_deg if walking else c.lean_backstop_deg
        if f.lean_angle > math.radians(backstop):
            return f"lean {math.degrees(f.lean_angle):.1f} deg beyond the {backstop:.0f} deg backstop"
        if walking:
            f.capture_point_error = capture_point_error(obs.state.capture_point, obs.state.feet_center, gait)
            if f.capture_point_error > c.walking_capture_point_error:
                return (f"walking: capture point {f.capture_point_error * 100:.1f} cm off the gait's reference "
                        f"(limit {c.walking_capture_point_error * 100:.1f} cm)")
            return ""
        if f.separatrix_margin > c.margin_threshold:
            return (f"energy over the leading edge {f.energy_ratio:.4f} of the crest "
                    f"(separatrix margin {f.separatrix_margin:+.4f} > {c.margin_threshold:+.4f})")
        return ""

    def step(self, obs: Observation) -> FtbStatus:
        """One tick: features, transitions, and the event on the tick the state leaves the boundary."""
        c = self.config
        if self.last_stamp is not None and obs.stamp_ns < self.last_stamp:
            self.reset()  # sim time went back: a new run
        self.last_stamp = obs.stamp_ns
        t = obs.time
        if self.state_since is None:
            self.state_since = t
        s = obs.state
        sole = obs.inputs.get("sole_polygon", getattr(s, "sole_polygon", None))
        f = features_of(s, sole if sole is not None and len(sole) else None)
        if self.weight is None and s.normal_force > 0 and math.isfinite(s.normal_force):
            self.weight = float(s.normal_force)
        loaded = self.weight is None or s.normal_force >= c.min_normal_force_fraction * self.weight
        if not loaded:
            f.valid = False
        reason = ""
        event = None
        cleared = None
        if self.com_height is None and math.isfinite(float(s.com[2])):
            self.com_height = float(s.com[2])
        # fallen: a loaded lean beyond the limit (an unloaded CoP is a fallback, its lean means
        # nothing: measured, a noisy quiet stance read > 60 deg), or the CoM down
        fallen = (f.valid and f.lean_angle > math.radians(c.fallen_lean_deg)) or \
            (self.com_height is not None and float(s.com[2]) < c.fallen_com_height_fraction * self.com_height)
        if self.state is FtbState.BALANCED:
            why = self._outside(obs, f)
            if why:
                if self.outside_since is None:
                    self.outside_since = t
                held = (t - self.outside_since) * 1e3 >= c.debounce_ms - 1e-6 or c.mode is TriggerMode.FIXED
                if held:
                    event = self._event(obs, f, why)
                    self._enter(FtbState.FALLING, t)
                    reason = why
            else:
                self.outside_since = None
            if event is None and fallen:
                self._enter(FtbState.FALLEN, t)
                reason = "fallen without a trigger"
        else:
            from_fallen = self.state is FtbState.FALLEN
            still = self._still(obs, f) if (not from_fallen or c.recover_from_fallen) else False
            if still:
                self.inside_since = t if self.inside_since is None else self.inside_since
            else:
                self.inside_since = None
            if fallen and not from_fallen:
                self._enter(FtbState.FALLEN, t)
                reason = f"lean beyond {c.fallen_lean_deg:.0f} deg"
            elif still and t - self.inside_since >= c.recover_s - 1e-9:
                cleared = self.event
                reason = (f"recovered{' from fallen' if from_fallen else ''}: inside the boundary, upright and "
                          f"still for {c.recover_s:.2f} s" + ("; fall event cleared" if cleared is not None else ""))
                self._enter(FtbState.BALANCED, t)
                self.outside_since = self.inside_since = None
                self.cleared_event = cleared
                self.event = None
            elif not from_fallen and t - self.state_since >= c.falling_timeout_s:
                self._enter(FtbState.FALLEN, t)
                reason = f"{c.falling_timeout_s:.1f} s in falling"
        return FtbStatus(obs.stamp_ns, self.state, c.mode.value, f, t - self.state_since, reason, event, self.event,
                         cleared)

    def _still(self, obs: Observation, f: FtbFeatures) -> bool:
        """Recovered this tick: inside the boundary, the P->G lean under ``recover_lean_deg``, the CoM slower
        than ``recover_speed`` and higher than ``recover_com_height_fraction`` of its first height (upright:
        a robot lying still is not recovered)."""
        c = self.config
        s = obs.state
        upright = self.com_height is None or float(s.com[2]) >= c.recover_com_height_fraction * self.com_height
        return bool(f.valid and upright and f.lean_angle < math.radians(c.recover_lean_deg)
                    and float(np.linalg.norm(np.asarray(s.com_velocity, float))) < c.recover_speed
                    and not self._outside(obs, f))

    def _enter(self, state: FtbState, t: float) -> None:
        self.state = state
        self.state_since = t

    def _event(self, obs: Observation, f: FtbFeatures, reason: str) -> FallEvent:
        c = self.config
        s = obs.state
        theta_thr = math.radians(c.theta_threshold_deg)
        duration = math.inf
        if f.valid and math.isfinite(f.theta):
            r = time_to_lean(f.theta, f.theta_dot, theta_thr, f.pendulum_length)
            duration = r.time if r.outcome is FallOutcome.FALLS else math.inf
        gait = gait_reference(obs.inputs.get("walking/state"))
        start = np.append(f.edge_start, 0.0) if f.valid else np.asarray(s.cop, float).copy()
        end = np.append(f.edge_end, 0.0) if f.valid else np.asarray(s.cop, float).copy()
        direction = math.atan2(f.edge_normal[1], f.edge_normal[0]) if f.valid else float(s.lean_direction)
        self.had_event = True
        self.event = FallEvent(
            obs.stamp_ns, c.mode.value, reason, start, end, bool(f.on_corner), np.asarray(s.cop, float).copy(),
            np.asarray(s.capture_point, float).copy(), direction, float(duration), theta_thr,
            float(f.energy_ratio), float(f.separatrix_margin), float(s.lean_angle), np.asarray(s.com, float).copy(),
            np.asarray(s.com_velocity, float).copy(), np.asarray(s.support_polygon, float).reshape(-1, 2).copy(),
            bool(gait is not None and gait.walking))
        return self.event


def edge_pendulum_of(s: CentroidalObservation, f: FtbFeatures):
    """The leading edge's pendulum (``toppling.EdgePendulum``) for a state and its features."""
    return edge_pendulum(s.com, s.com_velocity, np.append(f.edge_start, 0.0), f.edge_normal)


__all__ = ["TRANSITIONS", "FallEvent", "FtbConfig", "FtbFeatures", "FtbMonitor", "FtbState", "FtbStatus",
           "GaitRef", "GaitReference", "Transition", "TriggerMode", "capture_point_error", "edge_pendulum_of",
           "features_of", "gait_reference"]

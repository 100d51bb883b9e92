"""A library of precomputed fall plans and the warm-started online re-plan.

Paper 2 (Sec. V) names a database of optimal trajectories as the way to online
use. Here: plans are computed offline with the full tree search (Algorithm 1)
over a grid of pushes (kinetic energy [J], direction ±1, wall distance [m];
``build``); online, a request takes the nearest stored plan with the same
direction and wall presence (then the next nearest, up to ``max_entries``, while
none is accepted), keeps its contact sequence, and re-solves each of
its segments in order from the request's state with the stored segment as the
initial point, within the duration bounds the segment was planned with
(``TrajectoryOptimizer.warm_solve``: one IPOPT run per segment,
no seed sweep, no tree; IPOPT starts from the stored solution's multipliers as well, and a
segment that then fails, or a last one that does not stop, is solved once more from the primal
guess alone). Between segments the impact map of eq. 10 gives the
post-impact state of an added contact, as in the tree. The re-plan is accepted
when every segment converges, the last one ends below eps_KE and (the planner's
``library_check``) the plan passes the re-simulation check the tree applies;
otherwise the caller falls back to the tree search (``FallPlanner.plan``).
"""
from __future__ import annotations

import dataclasses
import gzip
import json
import math
import pathlib
import time

from humfall_ros.multicontact.collocation import OptConfig, Segment
from humfall_ros.multicontact.landing import LandingReport, landing_report
from humfall_ros.multicontact.modes import Environment, mode_label, one_foot_alone, parse_mode
from humfall_ros.multicontact.request import InvalidRequest, ValidRequest, validate

FORMAT = 1


@dataclasses.dataclass
class LibraryEntry:
    """One stored plan.

    Attributes:
        kinetic_energy: push energy [J].
        direction: +1 forward, -1 backward.
        wall_distance: [m], <= 0 no wall.
        contact_sequence: modes from the root.
        segments: transitions then the terminal self-motion.
        probes: push energy [J] -> whether this entry's re-plan there was accepted, tried offline
            (``PlanLibrary.probe``); online an entry whose probe failed on the request's side is tried
            after the others (``ranked``).
        derived_from: None for a plan of the tree search; else the push energy [J] of the entry this
            plan was re-solved from offline (``PlanLibrary.densify``: an accepted warm re-plan, stored).
    """

    kinetic_energy: float
    direction: float
    wall_distance: float
    contact_sequence: list[str]
    segments: list[Segment]
    probes: dict = dataclasses.field(default_factory=dict)
    derived_from: float | None = None

    def to_dict(self) -> dict:
        d = {"kinetic_energy": self.kinetic_energy, "direction": self.direction,
             "wall_distance": self.wall_distance, "contact_sequence": self.contact_sequence,
             "segments": [s.to_dict(multipliers=True) for s in self.segments]}
        if self.probes:
            d["probes"] = [[float(k), bool(v)] for k, v in sorted(self.probes.items())]
        if self.derived_from is not None:
            d["derived_from"] = float(self.derived_from)
        return d

    @staticmethod
    def from_dict(d: dict) -> "LibraryEntry":
        return LibraryEntry(float(d["kinetic_energy"]), float(d["direction"]), float(d["wall_distance"]),
                            list(d["contact_sequence"]), [Segment.from_dict(s) for s in d["segments"]],
                            {float(k): bool(v) for k, v in d.get("probes", [])},
                            None if d.get("derived_from") is None else float(d["derived_from"]))

    def fails_toward(self, kinetic_energy: float) -> bool:
        """A probe on the request's side of this entry failed, and the request is at least half way to it
        (a request next to the entry is nearly the stored plan itself)."""
        dk = kinetic_energy - self.kinetic_energy
        return any(not ok and (p - self.kinetic_energy) * dk > 0 and abs(dk) >= 0.5 * abs(p - self.kinetic_energy)
                   for p, ok in self.probes.items())


@dataclasses.dataclass
class Replan:
    """Result of a warm-started re-plan.

    Attributes:
        success: every segment converged and the last ends below eps_KE.
        reason: why not, or which entry was used.
        entry: the library entry used (None: none matched).
        segments: the re-solved segments (as far as they got).
        landings: severity of each landing (eq. 10).
        final_ke: [J].
        time_s: wall time of the re-plan [s].
        nlp_times_s: per segment [s].
    """

    success: bool
    reason: str
    entry: LibraryEntry | None
    segments: list[Segment]
    landings: list[LandingReport]
    final_ke: float
    time_s: float
    nlp_times_s: list[float]


class PlanLibrary:
    """Stored plans and the warm re-plan from them.

    ``built_with``: what the plans were made with (``n_knots``, ``transition_objective``; saved in the
    file): a planner whose NLPs differ in these cannot re-solve them (``check_compatible``). With
    ``step_capture_weight`` the re-plans solve the foot landings with that weight of the capture cost, the
    plans' own, whatever the planner's tree search uses (``capture_weight``)."""

    def __init__(self, entries: list[LibraryEntry] | None = None, built_with: dict | None = None):
        self.entries = list(entries or [])
        self.built_with = dict(built_with or {})

    @property
    def capture_weight(self) -> float | None:
        """The capture cost's weight the plans were made with (J/m^2; None: not recorded, the planner's)."""
        w = self.built_with.get("step_capture_weight")
        return None if w is None else float(w)

    def check_compatible(self, cfg: OptConfig) -> None:
        """ValueError unless every stored segment has ``cfg.n_knots`` knots, the library was built with
        ``cfg.transition_objective`` and ``cfg.step_capture_margin`` (when it says), and a library planned with a
        capture cost meets foot-landing NLPs that have it (``cfg.step_capture_weight`` 0 builds them without: the
        library's weight would be ignored)."""
        bad = {len(s.time) for e in self.entries for s in e.segments} - {cfg.n_knots}
        if bad:
            raise ValueError(f"plan library: segments with {sorted(bad)} knots, the planner's NLPs have "
                             f"{cfg.n_knots} (n_knots): rebuild the library")
        obj = self.built_with.get("transition_objective")
        if obj is not None and obj != cfg.transition_objective:
            raise ValueError(f"plan library built with transition_objective {obj!r}, the planner uses "
                             f"{cfg.transition_objective!r}: rebuild the library")
        margin = self.built_with.get("step_capture_margin")
        if margin is not None and abs(float(margin) - cfg.step_capture_margin) > 1e-9:
            raise ValueError(f"plan library built with step_capture_margin {margin:g}, the planner uses "
                             f"{cfg.step_capture_margin:g}: its re-plans would land steps the library did not "
                             f"plan for (rebuild the library, or use the one of that margin)")
        if (self.capture_weight or 0.0) > 0 and cfg.step_capture_weight <= 0:
            raise ValueError(f"plan library planned with step_capture_weight {self.capture_weight:g}, the planner's "
                             f"foot landings have no capture cost (step_capture_weight 0): rebuild the library")

    def without_single_foot_modes(self) -> "PlanLibrary":
        """The entries whose plans never stand on one foot alone after the push (``modes.one_foot_alone``;
        the planner's ``single_foot_modes`` false): a re-plan keeps its entry's contact sequence."""
        keep = [e for e in self.entries
                if not any(one_foot_alone(parse_mode(m)) for m in e.contact_sequence[1:])]
        return PlanLibrary(keep, self.built_with)

    def without_single_foot_ends(self) -> "PlanLibrary":
        """The entries whose plans do not end on one foot alone after the push (the planner's
        ``single_foot_terminal`` false): a re-plan keeps its entry's contact sequence."""
        keep = [e for e in self.entries
                if len(e.contact_sequence) < 2 or not one_foot_alone(parse_mode(e.contact_sequence[-1]))]
        return PlanLibrary(keep, self.built_with)

    # ------------------------------------------------------------- offline
    @staticmethod
    def build(planner, kinetic_energies, directions=(1.0,), wall_distances=(0.0,),
              time_budget: float = 120.0) -> "PlanLibrary":
        """Full tree searches over the grid; failed pushes are left out."""
        lib = PlanLibrary(built_with={"n_knots": planner.opt.cfg.n_knots,
                                      "transition_objective": planner.opt.cfg.transition_objective,
                                      "step_capture_weight": planner.opt.cfg.step_capture_weight,
                                      "step_capture_margin": planner.opt.cfg.step_capture_margin})
        for w in wall_distances:
            for d in directions:
                for ke in kinetic_energies:
                    r = planner.plan({"kinetic_energy": float(ke), "direction": float(d), "wall_distance": float(w),
                                      "time_budget": time_budget})
                    if r["success"]:
                        lib.entries.append(LibraryEntry(float(ke), float(d), float(w), r["contact_sequence"],
                                                        r["segments"]))
        return lib

    def save(self, path) -> None:
        """JSON, gzip-compressed when the name ends in ``.gz``."""
        text = json.dumps({"format": FORMAT, "built_with": self.built_with,
                           "entries": [e.to_dict() for e in self.entries]})
        p = pathlib.Path(path)
        if p.suffix == ".gz":
            p.write_bytes(gzip.compress(text.encode(), mtime=0))
        else:
            p.write_text(text)

    @staticmethod
    def load(path) -> "PlanLibrary":
        """A saved library (``.gz``: compressed; also the bare list of entries that sessions before 25 wrote)."""
        p = pathlib.Path(path)
        d = json.loads(gzip.decompress(p.read_bytes()) if p.suffix == ".gz" else p.read_text())
        if isinstance(d, list):
            return PlanLibrary([LibraryEntry.from_dict(x) for x in d])
        if d.get("format") != FORMAT:
            raise ValueError(f"plan library {path}: format {d.get('format')!r}, this code reads {FORMAT}")
        return PlanLibrary([LibraryEntry.from_dict(x) for x in d["entries"]], d.get("built_with"))

    def landings(self, model, limits=None) -> list[tuple[LibraryEntry, list[LandingReport]]]:
        """Each entry with the severity of its landings (eq. 10 at the end of each contact-adding
        segment, as the tree reports them)."""
        out = []
        for e in self.entries:
            env = Environment.from_distance(e.wall_distance)
            t, reps = 0.0, []
            for s in e.segments:
                t += float(s.time[-1])
                if s.change == "add":
                    reps.append(landing_report(model, s.q[-1], s.v[-1], s.target_mode, s.extremity, env, limits, t)[0])
            out.append((e, reps))
        return out

    # -------------------------------------------------------------- online
    def nearest(self, kinetic_energy: float, direction: float, wall_distance: float) -> LibraryEntry | None:
        """Same direction and wall presence; nearest in energy, then in wall distance."""
        ranked = self.ranked(kinetic_energy, direction, wall_distance)
        return ranked[0] if ranked else None

    def ranked(self, kinetic_energy: float, direction: float, wall_distance: float) -> list[LibraryEntry]:
        """The entries of the same direction and wall presence, nearest in energy first (then in wall
        distance); those whose offline probe failed on the request's side (``LibraryEntry.fails_toward``)
        after the rest."""
        has_wall = wall_distance > 0
        side = math.copysign(1.0, direction)
        cands = [e for e in self.entries
                 if math.copysign(1.0, e.direction) == side and (e.wall_distance > 0) == has_wall]
        return sorted(cands, key=lambda e: (e.fails_toward(kinetic_energy), abs(e.kinetic_energy - kinetic_energy),
                                            abs(e.wall_distance - wall_distance)))

    def probe(self, planner, log=None) -> None:
        """Offline: re-plan each entry at the energies half way to its neighbours (same direction and wall
        distance; an end entry as far out as its one neighbour is) and store whether that was accepted as
        the planner accepts a library answer (converged, stopped, and with ``library_check`` the
        re-simulation check; ``LibraryEntry.probes``). The online ranking then tries an entry that failed
        toward a request after the others (session 32: forward 16 J from the 15 J entry does not stop, from
        17.5 J it does; backward 11 / 12 J from the 10 J entry fail the check, from 15 J they pass)."""
        groups: dict = {}
        for e in self.entries:
            groups.setdefault((e.direction, e.wall_distance), []).append(e)
        for (direction, wall), group in groups.items():
            check_plan = planner.check_fn(Environment.from_distance(wall)) if planner.cfg.library_check else None
            group.sort(key=lambda e: e.kinetic_energy)
            kes = [e.kinetic_energy for e in group]
            for i, e in enumerate(group):
                halves = [(kes[j] - kes[i]) / 2 for j in (i - 1, i + 1) if 0 <= j < len(kes)]
                if len(halves) == 1:
                    halves.append(-halves[0])
                e.probes = {}
                for h in halves:
                    ke = kes[i] + h
                    if ke <= 0:
                        continue
                    vr = validate(planner.model, {"kinetic_energy": ke, "direction": direction,
                                                  "wall_distance": wall}, planner.cfg)
                    ok = self._attempt(planner, vr, e, time.perf_counter(), check_plan).success
                    e.probes[round(ke, 6)] = bool(ok)
                    if log is not None:
                        log(f"probe {e.kinetic_energy:g} J entry (direction {direction:+g}, wall {wall:g} m) "
                            f"at {ke:g} J: {'accepted' if ok else 'not accepted'}")

    def densify(self, planner, step: float, wall_distances=(0.0,), time_budget: float = 60.0,
                log=None) -> list[LibraryEntry]:
        """Offline continuation in the push energy: between each two neighbouring entries (same direction
        and wall distance, for the walls in ``wall_distances``; 0 = none) the energies ``step`` J apart
        from the lower one are answered as an online request would be (``replan``: nearest entries first,
        up to ``library_max_entries`` within ``library_max_ke_gap``, and with ``library_check`` the
        re-simulation check), and each accepted answer is stored as an entry (``derived_from`` its
        source's energy). Returns the new entries (already added).

        Why: an online re-plan spends most of its time in IPOPT iterations, and they grow with the
        distance to the stored plan, while a neighbour re-solved offline costs ~1 s. Measured (session 33:
        the shipped forward 2.5 J and backward 5 J grids densified to 1.25 J): forward 11-49 J within 1 s
        13 -> 19 of 19 queries, backward 16 -> 18 of 19 (docs/multicontact.md "Session 33").

        The sources are the entries there before this call, ranked by distance alone (their probes are
        not consulted, so the result does not depend on whether the library was probed yet); a new entry
        is not a source for the next one, so an error does not propagate along the chain."""
        if not step > 0:
            raise ValueError(f"densify step must be > 0 J, got {step!r}")
        walls = [float(w) for w in wall_distances]
        groups: dict = {}
        for e in self.entries:
            if any(abs(e.wall_distance - w) < 1e-9 for w in walls):
                groups.setdefault((e.direction, e.wall_distance), []).append(e)
        new: list[LibraryEntry] = []
        for (direction, wall), group in sorted(groups.items()):
            sources = PlanLibrary([dataclasses.replace(e, probes={}) for e in group], self.built_with)
            kes = sorted({e.kinetic_energy for e in group})
            check_plan = planner.check_fn(Environment.from_distance(wall)) if planner.cfg.library_check else None
            for lo, hi in zip(kes, kes[1:]):
                k = 1
                while lo + k * step < hi - 1e-6:
                    ke = round(lo + k * step, 6)
                    k += 1
                    rp = sources.replan(planner, {"kinetic_energy": ke, "direction": direction, "wall_distance": wall,
                                                  "time_budget": time_budget}, planner.cfg.library_max_ke_gap,
                                        planner.cfg.library_max_entries, check_plan)
                    if rp.success:
                        new.append(LibraryEntry(ke, direction, wall, list(rp.entry.contact_sequence), rp.segments,
                                                derived_from=rp.entry.kinetic_energy))
                    if log is not None:
                        log(f"densify direction {direction:+g}, wall {wall:g} m, {ke:g} J: "
                            + (f"re-solved from the {rp.entry.kinetic_energy:g} J entry in {rp.time_s:.1f} s"
                               if rp.success else f"not added ({rp.reason})"))
        self.entries += new
        self.entries.sort(key=lambda e: (e.wall_distance, -e.direction, e.kinetic_energy))
        return new

    def replan(self, planner, req: dict, max_ke_gap: float = math.inf, max_entries: int = 1,
               check_plan=None) -> Replan:
        """Re-solve the nearest entry's sequence from the request's state (see module doc; up to
        ``max_entries`` entries, nearest first, until one is accepted)."""
        t0 = time.perf_counter()
        try:
            vr = validate(planner.model, req, planner.cfg)
        except InvalidRequest as e:
            return Replan(False, f"invalid request: {e}", None, [], [], math.nan, time.perf_counter() - t0, [])
        return self.replan_valid(planner, vr, max_ke_gap, t0, max_entries, check_plan)

    def replan_valid(self, planner, vr: ValidRequest, max_ke_gap: float = math.inf,
                     t0: float | None = None, max_entries: int = 1, check_plan=None) -> Replan:
        """``replan`` for a validated request. The entries are chosen by the request state's kinetic
        energy and the sign of its centre of mass's forward velocity (a request may give a state
        rather than an energy and a direction); none further than ``max_ke_gap`` J. Up to
        ``max_entries`` of them are re-solved, nearest first, until one is accepted (a warm re-solve
        can end in another local optimum than its entry's; a neighbour is ~0.5 s, the tree search
        minutes); the result names every entry tried. ``check_plan(segments) -> reason | None``: the
        acceptance test of a re-plan besides convergence (the planner's re-simulation check, as the tree
        applies it before it declares a node terminal); a ``resim.PlanCheck`` checks each segment as it
        is solved (its ``start()``), any other callable the whole re-plan at the end."""
        t0 = time.perf_counter() if t0 is None else t0
        model = planner.model
        ke = model.kinetic_energy(vr.q, vr.v)
        vx = model.com_velocity(vr.q, vr.v)[0]
        ranked = self.ranked(ke, 1.0 if vx >= 0 else -1.0, vr.env.wall_x if vr.env.has_wall else 0.0)
        if not ranked:
            return Replan(False, "no library entry for this direction and environment", None, [], [], math.nan,
                          time.perf_counter() - t0, [])
        nearest = min(ranked, key=lambda e: abs(e.kinetic_energy - ke))   # ranked[0] may be a probe's pick
        if abs(nearest.kinetic_energy - ke) > max_ke_gap:
            return Replan(False, f"no library entry within {max_ke_gap:g} J of {ke:.1f} J (nearest "
                                 f"{nearest.kinetic_energy:g} J)", None, [], [], math.nan,
                          time.perf_counter() - t0, [])
        tried = [e for e in ranked if abs(e.kinetic_energy - ke) <= max_ke_gap][:max(1, max_entries)]
        failed: list[str] = []
        for entry in tried:
            if failed and _budget_spent(vr, t0):
                failed.append(f"{entry.kinetic_energy:g} J entry: not tried, the time budget of "
                              f"{vr.time_budget:g} s is spent")
                break
            rp = self._attempt(planner, vr, entry, t0, check_plan)
            if rp.success:
                break
            failed.append(f"{entry.kinetic_energy:g} J entry: {rp.reason}")
        if failed:   # the plan's own figures stay the accepted entry's; time_s counts every attempt
            rp.reason = rp.reason + " (after " + "; ".join(failed) + ")" if rp.success else "; ".join(failed)
        return rp

    def _attempt(self, planner, vr: ValidRequest, entry: LibraryEntry, t0: float, check_plan=None) -> Replan:
        """One entry's re-plan as the planner accepts it: converged and stopped (``_replan_entry``), then
        ``check_plan`` (a rejection makes it a failure that says why)."""
        start = getattr(check_plan, "start", None)
        checks = start() if start is not None else None
        rp = self._replan_entry(planner, vr, entry, t0, checks)
        if rp.success and check_plan is not None:
            why = checks.result() if checks is not None else check_plan(rp.segments)
            if why:
                rp.success = False
                rp.reason += f"; rejected by the re-simulation check: {why}"
            rp.time_s = time.perf_counter() - t0
        elif checks is not None:
            checks.cancel()
        return rp

    def _replan_entry(self, planner, vr: ValidRequest, entry: LibraryEntry, t0: float, checks=None) -> Replan:
        """One entry's warm re-plan (see module doc). ``checks`` (``resim.SegmentChecks``): each solved
        segment is handed to it at once, and the re-plan stops when one is already known to fail."""
        if mode_label(vr.mode) != entry.contact_sequence[0]:
            return Replan(False, f"library entry starts in {entry.contact_sequence[0]}, request in "
                                 f"{mode_label(vr.mode)}", entry, [], [], math.nan, time.perf_counter() - t0, [])
        q, v = vr.q, vr.v
        segs, lands, times = [], [], []
        t_plan = 0.0
        limits = planner.opt.cfg.landing_limits
        eps = planner.opt.cfg.eps_ke
        # an IPOPT run cannot be stopped from here: none is started once the budget is spent
        for i, stored in enumerate(entry.segments):
            if i > 0 and _budget_spent(vr, t0):
                return Replan(False, f"the time budget of {vr.time_budget:g} s is spent after {i} of "
                                     f"{len(entry.segments)} segments", entry, segs, lands, math.nan,
                              time.perf_counter() - t0, times)
            why = checks.failed() if checks is not None and i > 0 else None
            if why:
                return Replan(False, f"rejected by the re-simulation check after {i} of {len(entry.segments)} "
                                     f"segments: {why}", entry, segs, lands, math.nan, time.perf_counter() - t0, times)
            seg = planner.opt.warm_solve(q, v, stored, vr.env, capture_weight=self.capture_weight)
            spent = seg.nlp_time
            last = i == len(entry.segments) - 1
            if seg.attempt_log[0].get("multipliers") and (not seg.success or (last and seg.final_ke >= eps)) \
                    and not _budget_spent(vr, t0):
                # the stored multipliers led IPOPT to another local optimum (session 25: the 10 J stop
                # re-solved at 12 J ends at 0.80 J from them, at 0.0 J from the primal guess alone):
                # the primal start as well, the better of the two kept
                alt = planner.opt.warm_solve(q, v, stored, vr.env, multipliers=False,
                                             capture_weight=self.capture_weight)
                spent += alt.nlp_time
                if alt.success and (not seg.success or (last and alt.final_ke < seg.final_ke)):
                    alt.attempt_log = seg.attempt_log + alt.attempt_log
                    seg = alt
                else:
                    seg.attempt_log = seg.attempt_log + alt.attempt_log
            seg.nlp_time = spent
            segs.append(seg)
            times.append(spent)
            if checks is not None and seg.success:
                checks.add(seg, in_process=last)   # nothing else to do meanwhile: check it here
            if not seg.success:
                return Replan(False, f"warm-started {seg.kind} {mode_label(seg.mode)} -> "
                                     f"{mode_label(seg.target_mode)} did not converge ({seg.status})", entry, segs,
                              lands, math.nan, time.perf_counter() - t0, times)
            t_plan += float(seg.time[-1])
            q, v = seg.q[-1].copy(), seg.v[-1].copy()
            if seg.change == "add":
                rep, v = landing_report(planner.model, q, v, seg.target_mode, seg.extremity, vr.env, limits, t_plan)
                lands.append(rep)
        final = segs[-1].final_ke
        ok = final < planner.opt.cfg.eps_ke
        reason = (f"re-solved library plan for {entry.kinetic_energy:g} J "
                  f"({' -> '.join(entry.contact_sequence)}): final kinetic energy {final:.3g} J")
        return Replan(ok, reason if ok else reason + f" >= {planner.opt.cfg.eps_ke:g} J", entry, segs, lands,
                      final, time.perf_counter() - t0, times)


def _budget_spent(vr: ValidRequest, t0: float) -> bool:
    """The request's time budget, counted from ``t0``, is spent."""
    return time.perf_counter() - t0 >= vr.time_budget


__all__ = ["LibraryEntry", "PlanLibrary", "Replan"]

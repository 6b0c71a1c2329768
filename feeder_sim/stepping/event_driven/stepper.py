"""``event_driven``: the paper's scheme (accuracy method).

Between events the bodies move smoothly under gravity, prescribed track motion and contact
forces. The contact *mode* — which contacts press (normal force, zero normal acceleration),
which stick (zero tangential acceleration) and which slide (friction ``-sigma mu_d f_N``) — is
chosen by Baraff's frictional force LCP at the start of a phase and then held. Each phase
watches event functions; the first one to cross zero ends the phase at the located time:

=====================  ============================================  =====================
event                  function that must stay >= 0                  what happens
=====================  ============================================  =====================
collision              distance of a corner outside a nearby piece   impulse LCP (Kawachi)
lift-off / tipping     normal force of a pressing contact            new force LCP
stick -> slip          mu_s sum f_N - |sum f_T| of a sticking group  new force LCP
slip -> stick/reverse  sigma v_T of a sliding contact                new force LCP
sliding off an edge    edge parameter in [0, 1]                      new contact detection
=====================  ============================================  =====================

At a normal-force event the force LCP is degenerate for the contact whose force reached zero
(no force, and a separating acceleration still below the LCP's tolerance): a tall block's
trailing corner as the platform's acceleration passes g b / h. A contact the LCP gives no force
and whose force in the held mode is already past its event leaves the mode
(``kern.leaving``, :meth:`EventDriven._hold`): held, it would press with a negative force no
event watches, and the block would never tip.

Phases are followed in one of two ways:

* **Closed form**, when every dynamic body either flies free (no held contact) or translates
  without turning against static or sinusoidally driven bodies, touching them only with its
  own vertices (a box lying, sticking or sliding on a track). The held mode's equations are
  then linear with constant coefficients in gravity and the drives' accelerations ``s(t)``, so
  one least-squares solve at the phase start gives every body's acceleration
  ``phi0 + phi1 s(t)`` and every contact force ``f0 + f1 s(t)``; positions, velocities,
  forces and the transmitted impulses follow exactly from the drives' sinusoids. Nothing is
  integrated: the events are evaluated at the ends of steps of the largest step size (or
  shorter, see below) and a crossing is located by Illinois regula falsi on the exact state.
* **Integrated** otherwise (a body rotating on a corner, bodies pressing on each other): a
  Dormand–Prince 5(4) integrator with error control follows the held mode, and an event is
  located by Illinois regula falsi on full integrator steps from the step start. The
  right-hand side (contact geometry, Jacobian, the held mode's least-squares forces, event
  functions) and the steps are compiled; while a drive blends after a command it is not a
  plain sinusoid, and a Python right-hand side that asks the drives takes over.

The kernels are in :mod:`._kernels`. A single dynamic body's closed-form phases are chained in
compiled code (:mod:`._chain`) through the events its own contacts resolve (a slip stopping or
reversing, static friction giving way, a lift-off, a corner landing on a face): Python then sees
only the rest (a corner leaving its edge, touching near a corner, an LCP the pivoting misses, a
mode without closed form).

Candidate collisions are the active corners of every piece against every other piece whose
bounding box lay within a margin when they were detected; they are detected again only when a
body may have moved half that margin since (in closed form from a bound on the exact
velocities, when integrating from a heuristic reach per step). A collision is a candidate's gap
(the corner's largest signed distance from the piece's edge lines) dropping below zero; lines
the corner lies flush on with its own piece on their inner side are left out, or blocks meeting
face-on with aligned corners, every corner on the line of a side face of the other block, would
never show a negative gap. No step lets a corner travel, relative to a candidate piece, farther
than its gap plus half the piece's minimum width (conservative advancement): a fast part cannot
pass through a thin wall between two event tests, and a slow or distant one does not shorten
the step.

The impulse and force LCPs first try the final active set of the last pivoting solve of a
problem of the same shape and keep it when the LCP residual accepts it: the events of a
periodic motion pose nearly the same problems every cycle.

Parallel contacts between the same two bodies (an edge lying on an edge, or a part
overhanging a track's end: its corner on the track and the track's corner on it) share their
loads in a way rigid-body mechanics leaves open, so friction is tested on the group's totals,
both when a phase is held and when the force LCP's answer picks the next mode (an answer may
squeeze the group, one contact's friction at +mu f_N and another's at -mu f_N: the group still
sticks).
When the force LCP has no solution (Painlevé configurations: a rod sliding on its tip with
much friction, a box thrown along the floor with mu above its aspect ratio) a contact that
slides on a ray along which its normal velocity falls takes Génot & Brogliato's tangential
impact (``ContactModes.impact_without_collision``): it presses in and stops slipping
although it did not approach. The contacts that separate after it leave the mode, and the
force LCP is solved again. If it still has no answer, the fallback answer is used, counted
(``unresolved_force_lcps``) and reported; so is any LCP the fallback ladder answered without
friction (``frictionless_answers``): the run logs it once, the summary counts it and the node's
``/diagnostics`` turns to ERROR.

Rocking or bouncing to rest accumulates impacts (Zeno: a square with e = 0 keeps a quarter of
its angular velocity at each impact, so the swings shrink geometrically and end after
infinitely many impacts in a finite time). After an impact, a touching corner that leaves
slower than gravity along its normal can lift it past ``touch_m`` ends the accumulation where
it converges (``ContactModes.close_accumulation``): the touching contacts take the
minimum-energy impulse that stops their normal motion, counted as ``zeno_closures``. A 20 mm
square released 0.2 rad from flat settles after 6 impacts instead of stalling.

A slip stops where its event function has passed the event threshold, the slip reversed by
up to that threshold times the speed scale (~3e-10 m/s for a 20 mm part); a sticking mode
would keep that speed, and a stopped part would creep. The mode choice (Python's and the
chain's) ends it with the minimum-energy impulse that brings the held contacts to rest,
counted as ``slip_closures``: a box launched at 0.5 m/s stops where v0^2 / (2 a) says and
moves less than a picometre in the 5 s after.
"""

from __future__ import annotations

import math

import numpy as np

from feeder_sim.model.world import State
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.event_driven import phases
from feeder_sim.stepping.event_driven.bookkeeping import (
    EVENT_THRESHOLD,
    EventSettings,
    FORCE_TOL_REL,
    GIVE_WAY_S,
    make_setup,
    Mode,
    pack,
    unpack,
)
from feeder_sim.stepping.event_driven.events import CandidateWatch, Integrator, largest_step
from feeder_sim.stepping.event_driven.modes import ContactModes, held_arrays, ModeChoice
from feeder_sim.stepping.protocol import StepContacts, StepperBase

__all__ = ['EventDriven', 'EventSettings']

# ``kern.leaving``'s drives for forces given at one instant
NO_DRIVES = kern.Drives(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0),
                        np.zeros(0), 0.0)


class EventDriven(StepperBase):
    """Advances a state to any requested time, stopping at every contact event."""

    settings_type = EventSettings
    name = 'event_driven'
    fixed_steps = False
    error_setting = 'tolerance'
    order = None          # its error is no known power of its tolerance

    def prepare(self) -> None:
        world, spec = self.world, self.spec
        self.setup = make_setup(world, spec, self.settings)
        self.modes = ContactModes(world, self.setup, self.settings, spec.friction_impulse,
                                  self.stats)
        self.watch = CandidateWatch(world, self.setup)
        self.integrator = Integrator(world, self.setup, spec.tolerance, spec.time_step)
        self.drive_models = phases.DriveModels(world)
        self._mode: Mode | None = None
        self._h = spec.time_step
        self._pending: list[StepContacts] = []
        self._give_way_s, self._last_cascade_t = GIVE_WAY_S, -math.inf

    def reset(self) -> None:
        self._mode = None
        self.watch.near = None
        self.drive_models.clear()
        self._h = self.spec.time_step
        self._pending = []
        self._give_way_s, self._last_cascade_t = GIVE_WAY_S, -math.inf

    def h_max(self) -> float:
        """The largest step (s): the scene's, at most a sixteenth of every drive's period."""
        return largest_step(self.world, self.spec.time_step)

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Integrate ``state`` in place to ``t_end``; returns the contact impulses transmitted."""
        scratch = state.copy()
        events_here, last_event_t = 0, -math.inf
        reported = len(self._pending)
        while state.t < t_end - 1e-15:
            if self._mode is None:
                self._settle(state)
                reported = self._checkpoint(state, reported)
            t_stop = t_end
            for i in self.world.driven:
                t_stop = min(t_stop, self.world.drives[i].next_change_after(state.t))
            if self._mode.phase is not None:
                hit = self._follow_phase(state, t_stop)
            else:
                hit, self._h = self.integrator.step(self._mode, state, t_stop, self._h,
                                                    scratch, self.watch, self._pending,
                                                    self.stats)
            if hit:
                self._mode = None
                self.stats.events += 1
                reported = self._checkpoint(state, reported)
                dense = state.t - last_event_t < self.settings.cascade_window_s
                events_here = events_here + 1 if dense else 0
                last_event_t = state.t
                again = state.t - self._last_cascade_t <= self.settings.cascade_memory_s
                if events_here > (self.settings.max_events_again if again else
                                  self.settings.max_events_at_one_time):
                    # A cascade: events at one instant, or a mode that chatters between two
                    # choices every few nanoseconds (a contact at its friction bound touched by
                    # a corner, two corners trading which lies on whose edge). Step past it,
                    # twice as far each time it comes back within the memory.
                    if not again:
                        self._give_way_s = GIVE_WAY_S
                    self._give_way(state, scratch, self._give_way_s)
                    self._give_way_s = min(2.0 * self._give_way_s,
                                           self.settings.max_give_way_s)
                    self._last_cascade_t = state.t
                    events_here = 0
                continue
            if state.t >= t_stop - 1e-15 and t_stop < t_end:
                self._mode = None   # the drive's acceleration has a kink here
        out, self._pending = self._pending, []
        return out

    def _checkpoint(self, state: State, reported: int) -> int:
        """At an event (before and after its impulses): hand ``after_event`` the contacts
        reported since index ``reported`` of the pending list; returns the new index."""
        if self.after_event is not None:
            self.after_event(state, self._pending[reported:])
        return len(self._pending)

    def _follow_phase(self, state: State, t_stop: float) -> bool:
        """Follow the held closed-form mode to t_stop or its first event; True at an event."""
        args = (self.world, self.setup, self._mode, state, t_stop, self.h_max(), self.watch,
                self.drive_models, self._pending, self.stats)
        if self.setup.chained and self.after_event is None:
            # (the chain resolves events in compiled code; a check per event needs them here)
            hit, self._mode = phases.follow_chain(*args)
            return hit
        return phases.follow_closed_form(*args)

    def _settle(self, state: State) -> None:
        """Resolve collisions at the current instant, then hold the next contact mode."""
        self._hold(state, self.modes.settle(state, self._pending))

    def _hold(self, state: State, choice: ModeChoice) -> None:
        """Hold a mode from ``state`` on: closed form if it has one, else integrated. A
        contact the mode cannot keep (``kern.leaving``: no LCP force, its own force already
        past its event) leaves it first."""
        while True:
            held, n_events = held_arrays(self.setup, choice.features, choice.friction,
                                         choice.sigma, choice.group, choice.material.mu_static)
            mode = self._mode = Mode(choice.features, choice.friction, choice.sigma,
                                     choice.group, choice.material, held, n_events)
            model = self.drive_models.at(state.t)
            mode.phase = phases.closed_form(self.world, self.setup, mode, state, choice.cs,
                                            model)
            leave = self._leaving(state, choice, mode, model)
            if not leave.any():
                break
            choice = choice.without(leave)
        if mode.phase is None:
            mode.spec = phases.compiled_rhs(self.world, self.setup, mode, state, model)

    def _leaving(self, state: State, choice: ModeChoice, mode: Mode,
                 model: phases.DriveModel | None) -> np.ndarray:
        """(k,) the held contacts of ``mode`` that ``kern.leaving`` lets go at ``state``."""
        setup = self.setup
        force_tol = setup.force_scale * FORCE_TOL_REL
        k = choice.features.n
        if not k or choice.force_n.min() > force_tol:
            return np.zeros(k, bool)    # every contact presses: nothing degenerate
        ph = mode.phase
        if ph is not None:
            drives, f0, f1 = ph.drives, ph.f0, ph.f1
        else:
            # the integrated mode's forces now (the drives' terms are in them)
            f0 = self.integrator.rhs(mode, state.t, pack(setup.dyn, state),
                                     state.copy())[1]['f_n']
            drives, f1 = NO_DRIVES, np.zeros((k, 0))
        return kern.leaving(state.t, drives, choice.force_n, np.ascontiguousarray(f0, float),
                            np.ascontiguousarray(f1, float), force_tol,
                            EVENT_THRESHOLD * setup.force_scale)

    def _give_way(self, state: State, scratch: State, h: float) -> None:
        """Many events in a moment: let the mode run a step of ``h`` (s) without watching its
        events, to break the tie; a collision it leads into is resolved at the next settle."""
        self.stats.cascades += 1
        if self.stats.cascades <= 20:
            self.stats.messages.append(f'event cascade at t={state.t:.9f}s; stepped {h:.1e} s '
                                       'past it')
        self._settle(state)
        mode, dyn = self._mode, self.setup.dyn
        self.watch.for_step(mode, state, h)
        y = pack(dyn, state)
        k0 = self.integrator.evaluate(mode, state.t, y, scratch)[0]
        y1 = self.integrator.dopri_step(mode, state.t, y, h, k0, scratch)[0]
        unpack(self.world, dyn, state.t + h, y1, state)
        self._mode = None

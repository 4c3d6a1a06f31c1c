"""`Sequence`: controllers concatenated in time at transition points (the second paper's
composite motion, section 3, Figures 13 and 14)."""

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .base import AbstractController, ControllerState


class SequenceState(eqx.Module):
    """The discrete state of a `Sequence` (its `ControllerState.discrete`).

    - `phase`: the index of the controller in charge (0 for the first).
    - `children`: each controller's own discrete state (a later controller's is a
        placeholder until its phase starts, when it is made afresh).
    """

    phase: Int[Array, ""]
    children: tuple[Any, ...]


class Sequence(AbstractController):
    """K controllers run one after another: controller `k` from transition `k - 1` to
    transition `k` (the first from the start, the last to the end), the body's state
    carried across (the second paper's composite motion, section 3).

    Each controller runs as if it were simulated alone from where the body is when its
    phase starts: at the control tick of transition `k - 1` it starts from its own initial
    state (`init`, given the senses there) at its own time 0, and from then on it sees its
    *local* time, the time since its phase began (so a time-based controller starts its
    script afresh). For a sense-based controller (`SenseBSR`) that means rule 0 through its
    first tick and its low-pass filter starting at the present senses: not the previous
    controller's rule (whose rules mean nothing to it) nor that one's filtered senses (which
    lag the body by the previous controller's filter time, when it has one at all). This is
    the state each controller was found from in its own search, and it makes a composite
    exactly the controllers run one after another from the carried state: on the
    fixed-step path, a `Sequence` computes bitwise what simulating controller 0 for `[0,
    T_1]`, then controller 1 from the final body state for `[0, T_2 - T_1]`, and so on,
    computes. (A robust controller, found from perturbed starts, is what makes such a start
    safe: see the second paper's "enhanced motion controllers".)

    Transitions are placed on the control ticks: transition `k` takes effect at the tick
    `round(T_k / control_dt)` (a transition between ticks moves to the nearest), and equal
    transitions skip the phases between them. A transition past the simulation's end is
    never reached.

    Every controller's state is carried through the whole simulation (the later ones' are
    placeholders until their phase starts) and every controller's tick is computed at every
    tick, the inactive ones' discarded: the choice is elementwise, so a batch of sequences
    with different transitions runs as one vectorised program (`Task.evaluate` over a
    batch of transition arrays). A tick costs the sum of the controllers' ticks.

    **Fields:**

    - `controllers`: the K controllers, in order (any mix of families, for one body: their
        actuations must have the same shape).
    - `transitions`: `(K - 1,)` the transition times, s, ascending and >= 0.
    - `control_dt` (static): the control period, s, set by the simulation
        (`on_grid`); `None` until then.

    **Raises:** `TypeError` for a controller that is not an `AbstractController`;
    `ValueError` for no controllers, or transitions that are not `K - 1` finite, ascending
    times >= 0.
    """

    controllers: tuple[AbstractController, ...]
    transitions: Float[Array, " K-1"]
    control_dt: float | None = eqx.field(static=True)

    supports_batch_last = True

    def __init__(
        self,
        controllers,
        transitions: Float[ArrayLike, " K-1"],
        control_dt: float | None = None,
    ):
        controllers = tuple(controllers)
        if not controllers:
            raise ValueError("Sequence needs at least one controller; got none")
        for i, c in enumerate(controllers):
            if not isinstance(c, AbstractController):
                raise TypeError(
                    f"Sequence.controllers[{i}] must be a controller (an AbstractController); "
                    f"got {type(c).__name__}"
                )
        if not isinstance(transitions, jax.core.Tracer) and np.ndim(transitions) == 1:
            _check_transitions(np.asarray(transitions, dtype=float), len(controllers))
        self.controllers = controllers
        self.transitions = jnp.asarray(transitions, dtype=float)
        self.control_dt = None if control_dt is None else float(control_dt)

    @property
    def num_phases(self) -> int:
        return len(self.controllers)

    @property
    def reads_senses(self) -> bool:  # type: ignore[override]
        """Whether any of the controllers reads the body's senses."""
        return any(c.reads_senses for c in self.controllers)

    def on_grid(self, control_dt: float) -> "Sequence":
        """This sequence (and its controllers) run with control ticks `control_dt` apart."""
        children = tuple(c.on_grid(control_dt) for c in self.controllers)
        return dataclasses.replace(self, controllers=children, control_dt=control_dt)

    # ------------------------------------------------------------------ the layout

    def _batched(self) -> bool:
        """Whether this is a batch-last stack (transitions `(K - 1, batch)`)."""
        return self.transitions.ndim == 2

    def _call(self, child: AbstractController, name: str, *args):
        """`child.name(*args)` in this sequence's layout: directly, or `vmap`ped over the
        last axis of every argument for a batch-last stack of a controller that does not
        support that layout. Arguments that are `None` are passed as they are."""
        method = getattr(type(child), name)
        if not self._batched() or type(child).supports_batch_last:
            return method(child, *args)
        axes = tuple(None if a is None else -1 for a in args)
        return jax.vmap(method, in_axes=(-1, *axes), out_axes=-1)(child, *args)

    def _period(self, t):
        """The control period in the time's dtype."""
        return jnp.asarray(self.control_dt, dtype=jnp.result_type(t))

    @staticmethod
    def _phase_start(phase, starts):
        """The first tick of `phase` (0 for the first phase), by a chain of selects."""
        start = jnp.zeros(jnp.shape(phase), dtype=jnp.int32)
        for k in range(starts.shape[0]):
            start = jnp.where(phase == k + 1, starts[k], start)
        return start

    # ------------------------------------------------------------------ the controller

    def prepare(self, body) -> tuple[tuple[Any, ...], Int[Array, " K-1"]]:
        """Every controller's plan, and the transitions' tick indices."""
        if self.control_dt is None:
            raise ValueError(
                "Sequence.control_dt is not set: simulate it with jaxmotion.simulate or a "
                "Task (they set it from the control period), or call on_grid(control_dt) first"
            )
        plans = tuple(self._call(c, "prepare", body) for c in self.controllers)
        h = jnp.asarray(self.control_dt, dtype=self.transitions.dtype)
        starts = jnp.round(self.transitions / h).astype(jnp.int32)
        return plans, starts

    def _senses_for(self, child, senses):
        return senses if child.reads_senses else None

    def init(self, senses, plan) -> ControllerState:
        """Phase 0; every controller in its initial state (given the starting senses)."""
        plans, starts = plan
        states = [
            self._call(c, "init", self._senses_for(c, senses), p)
            for c, p in zip(self.controllers, plans, strict=True)
        ]
        phase = jnp.zeros(jnp.shape(starts)[1:], dtype=jnp.int32)
        return _joined(phase, states)

    def update(self, t, state: ControllerState, senses, plan) -> ControllerState:
        """The tick: the phase of the tick's time; a controller whose phase starts here
        starts from its initial state; the controller in charge ticks at its local time."""
        plans, starts = plan
        h = self._period(t)
        # Whole tick counts: `t` is `n h` rounded once (the solvers' tick times), so `n` is
        # exact, and the local time `(n - start) h` is computed as a simulation started at
        # the phase's start computes its own tick times (bitwise).
        tick = jnp.round(t / h).astype(jnp.int32)
        phase = jnp.sum((tick >= starts).astype(jnp.int32), axis=0)
        local = (tick - self._phase_start(phase, starts)).astype(h.dtype) * h
        old = state.discrete.phase
        states = []
        for k, (child, child_plan, own) in enumerate(
            zip(self.controllers, plans, _split(state, self.num_phases), strict=True)
        ):
            child_senses = self._senses_for(child, senses)
            fresh = self._call(child, "init", child_senses, child_plan)
            start = _where((phase == k) & (old != k), fresh, own)
            ticked = self._call(child, "update", local, start, child_senses, child_plan)
            states.append(_where(phase == k, ticked, own))
        return _joined(phase, states)

    def _local(self, t, state: ControllerState, plan):
        """The phase in charge and the time since it began, at `t` within a period."""
        h, starts = self._period(t), plan[1]
        phase = state.discrete.phase
        return phase, t - self._phase_start(phase, starts).astype(h.dtype) * h

    def actuation(self, t, state: ControllerState, plan):
        """The actuation of the controller in charge, at its local time."""
        plans, _ = plan
        phase, local = self._local(t, state, plan)
        out = None
        for k, (child, child_plan, own) in enumerate(
            zip(self.controllers, plans, _split(state, self.num_phases), strict=True)
        ):
            mine = self._call(child, "actuation", local, own, child_plan)
            out = mine if out is None else _where(phase == k, mine, out)
        return out

    def rates(self, t, state: ControllerState, plan):
        """The controller in charge moves its continuous state; the others' stay put."""
        if state.continuous is None:
            return None
        plans, _ = plan
        phase, local = self._local(t, state, plan)
        positions, velocities = [], []
        for k, (child, child_plan, own) in enumerate(
            zip(self.controllers, plans, _split(state, self.num_phases), strict=True)
        ):
            if own.continuous is None:
                positions.append(None)
                velocities.append(None)
                continue
            dx, dv = self._call(child, "rates", local, own, child_plan)
            zero = lambda tree: jax.tree_util.tree_map(jnp.zeros_like, tree)
            positions.append(_where(phase == k, dx, zero(dx)))
            velocities.append(_where(phase == k, dv, zero(dv)))
        return tuple(positions), tuple(velocities)

    def perceive(self, t, state: ControllerState, senses, plan):
        """What the controller in charge perceives (the senses themselves for one that does
        not read them)."""
        plans, _ = plan
        phase, local = self._local(t, state, plan)
        out = senses
        for k, (child, child_plan, own) in enumerate(
            zip(self.controllers, plans, _split(state, self.num_phases), strict=True)
        ):
            if not child.reads_senses:
                continue
            mine = self._call(child, "perceive", local, own, senses, child_plan)
            out = jnp.where(phase == k, mine, out)
        return out

    def smoothed(self, width: float) -> "Sequence":
        """Every controller smoothed (`AbstractController.smoothed`)."""
        children = tuple(c.smoothed(width) for c in self.controllers)
        return dataclasses.replace(self, controllers=children)


def _check_transitions(transitions: np.ndarray, num_phases: int) -> None:
    if transitions.shape != (num_phases - 1,):
        raise ValueError(
            f"Sequence.transitions has shape {transitions.shape}; allowed: ({num_phases - 1},), "
            f"one time between each pair of the {num_phases} controllers"
        )
    if not np.all(np.isfinite(transitions)) or np.any(transitions < 0):
        raise ValueError(
            f"Sequence.transitions = {transitions.tolist()}; allowed: finite times >= 0 (s)"
        )
    if np.any(np.diff(transitions) < 0):
        raise ValueError(
            f"Sequence.transitions = {transitions.tolist()} are not ascending; allowed: "
            "T_1 <= T_2 <= ... (controller k runs from T_k to T_k+1)"
        )


def _split(state: ControllerState, num: int) -> list[ControllerState]:
    """The controllers' own states (see `_joined`)."""
    if state.continuous is None:
        pairs = [None] * num
    else:
        positions, velocities = state.continuous
        pairs = [None if x is None else (x, v) for x, v in zip(positions, velocities, strict=True)]
    return [ControllerState(d, p) for d, p in zip(state.discrete.children, pairs, strict=True)]


def _joined(phase, states: list[ControllerState]) -> ControllerState:
    """The sequence's state from the phase and every controller's own state: continuous
    `None` when no controller has a continuous part, else `(positions, velocities)` each a
    tuple over the controllers (`None` for one without)."""
    discrete = SequenceState(phase, tuple(s.discrete for s in states))
    if all(s.continuous is None for s in states):
        return ControllerState(discrete)
    positions = tuple(None if s.continuous is None else s.continuous[0] for s in states)
    velocities = tuple(None if s.continuous is None else s.continuous[1] for s in states)
    return ControllerState(discrete, (positions, velocities))


def _where(condition, a, b):
    """`a` where `condition`, else `b`, leaf by leaf (a batch-last condition `(batch,)`
    broadcasts against the trailing batch axis of every leaf)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(condition, x, y), a, b)

"""The closed loop of a body and a controller: the per-step functions every solver and every
layout runs (senses, control tick, rates, samples), written once.

A simulation is a hybrid system (`notes/closed-loop.md`):

- continuous state: the body's `(positions, velocities)` and the controller's continuous part,
  integrated together;
- discrete state: the controller's `discrete` part, changed only at control ticks
  `t_k = k control_dt`: `d <- update(t_k, d, senses(x(t_k)))`, then held until `t_{k+1}`.

`ClosedLoop` holds the pieces of one simulation and exposes the functions the solvers call.
Its `batched` layout runs a batch of controllers with the batch as the *last* axis of every
array (so XLA's CPU loops vectorise over controllers): the same functions, called directly on
the batch by bodies and controllers that support it (`supports_batch_last`) and `vmap`ped over
the last axis otherwise. The state the solvers carry is `(BodyState, ControllerState)`.
"""

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._body.base import AbstractDynamics, BodyState
from .._control.base import AbstractController, ControllerState
from .._world import World
from .trajectory import Observation


class ClosedLoop(eqx.Module):
    """One body driven by one controller (or a batch of them, `batched`) in a world.

    - `dynamics`: the body prepared for simulation.
    - `controller`: the controller (`None`: no actuation); batch-last when `batched`.
    - `plan`: `controller.prepare(body)`, laid out like the controller.
    - `world`: gravity, floor, contact.
    - `control_dt`: the control period, s.
    - `batched`: whether every state, controller and plan leaf has a trailing batch axis.
    - `record_senses`: whether samples include the senses the controller perceives.
    - `record_positions`: whether samples include the body's positions state (what rebuilds
        a figure's whole pose; the search never asks for it).
    - `control_dtypes`: the dtypes of the controller's state leaves (`with_start`).
    """

    dynamics: AbstractDynamics
    controller: AbstractController | None
    plan: Any
    world: World
    control_dt: float = eqx.field(static=True)
    batched: bool = eqx.field(static=True, default=False)
    record_senses: bool = eqx.field(static=True, default=False)
    record_positions: bool = eqx.field(static=True, default=False)
    control_dtypes: Any = eqx.field(static=True, default=None)

    # ------------------------------------------------------------------ layout

    def _body(self, name: str, batched: tuple, shared: tuple = ()):
        """`dynamics.name(*batched, *shared)` for this layout: called directly on a batch by
        dynamics that support trailing batch axes, else `vmap`ped over the last axis of the
        `batched` arguments (see `_body_method`)."""
        vmapped = self.batched and not type(self.dynamics).supports_batch_last
        return _body_method(self.dynamics, name, vmapped, batched, shared)

    def _control(self, name, in_axes):
        """`type(controller).name` as a function of the controller and the method's other
        arguments (`in_axes` says which carry the batch: -1, or None for shared ones)."""
        method = getattr(type(self.controller), name)
        if not self.batched or type(self.controller).supports_batch_last:
            return method
        return jax.vmap(method, in_axes=(-1, *in_axes), out_axes=-1)

    @property
    def reads_senses(self) -> bool:
        return self.controller is not None and bool(self.controller.reads_senses)

    def restore(self, control: ControllerState) -> ControllerState:
        """The controller's state in its own dtypes. diffrax carries every leaf of the
        simulation state in the time's floating dtype (an integer such as an active rule's
        index stays exact there); the controller always sees the dtypes its `init` gives."""
        if self.control_dtypes is None:
            return control
        return jax.tree_util.tree_map(lambda a, d: a.astype(d), control, self.control_dtypes)

    def with_start(self, control: ControllerState) -> "ClosedLoop":
        """This system, remembering the dtypes of the controller's state (see `restore`)."""
        dtypes = jax.tree_util.tree_map(lambda a: jnp.result_type(a), control)
        return dataclasses.replace(self, control_dtypes=dtypes)

    # ------------------------------------------------------------------ the loop's pieces

    def senses(self, body: BodyState):
        """The body's senses (`(num_senses, *batch)`)."""
        return self._body("senses", (body,), (self.world, self.control_dt))

    def start(self, body: BodyState) -> ControllerState:
        """The controller's state before its first tick (`init`, given the senses of the
        starting state)."""
        if self.controller is None:
            return ControllerState()
        senses = self.senses(body) if self.reads_senses else None
        return self._control("init", (-1, -1))(self.controller, senses, self.plan)

    def tick(self, t, body: BodyState, control: ControllerState) -> ControllerState:
        """The control tick at `t`: the controller's state for the period from `t`, updated
        from the time and the body's senses."""
        if self.controller is None:
            return control
        senses = self.senses(body) if self.reads_senses else None
        update = self._control("update", (None, -1, -1, -1))
        new = update(self.controller, t, self.restore(control), senses, self.plan)
        # Back in the carried dtypes (see `restore`).
        return jax.tree_util.tree_map(lambda a, c: a.astype(c.dtype), new, control)

    def rates(self, t, positions, velocities, discrete):
        """Rates of the continuous state, `(positions, velocities)` each a pair `(body,
        controller continuous part)`, with the discrete controller state held at
        `discrete`."""
        body = BodyState(positions[0], velocities[0])
        continuous = None if positions[1] is None else (positions[1], velocities[1])
        actuation = None
        if self.controller is not None:
            control = self.restore(ControllerState(discrete, continuous))
            actuation = self._control("actuation", (None, -1, -1))(
                self.controller, t, control, self.plan
            )
        body_rates = self._body("rates", (body, actuation), (self.world,))
        if continuous is None:
            return (body_rates.positions, None), (body_rates.velocities, None)
        c_pos, c_vel = self._control("rates", (None, -1, -1))(
            self.controller, t, control, self.plan
        )
        return (body_rates.positions, c_pos), (body_rates.velocities, c_vel)

    def sample(self, t, y, args=None) -> tuple[Observation, Any, Any]:
        """What is saved at a sample: the observables, (if recorded) the senses the
        controller perceives at the tick here and (if recorded) the body's positions."""
        del args
        body, control = y
        obs = self._body("observe", (body.positions,), (self.world,))
        positions = body.positions if self.record_positions else None
        if not self.record_senses:
            return obs, None, positions
        senses = self.senses(body)
        if self.controller is not None:
            perceive = self._control("perceive", (None, -1, -1, -1))
            senses = perceive(self.controller, t, self.restore(control), senses, self.plan)
        return obs, senses, positions


@functools.partial(eqx.filter_jit, inline=True)
def _body_method(dynamics, name: str, vmapped: bool, batched: tuple, shared: tuple):
    """`dynamics.name(*batched, *shared)`, `vmap`ped over the last axis of `batched` when
    `vmapped`.

    diffrax traces a solver's step several times (shape checks, the loop body), the step
    evaluates the rates twice and reads the senses at every tick: under `jit(inline=True)`
    every call with the same shapes reuses one trace, inlined where it is called (the
    computation is unchanged). Measured on sense-based Star-Man: the rates traced 5 times
    and the contact model 8 times before; tracing took 1.3-1.9 s of the first call, 0.8-1.1 s
    after."""
    fn = lambda *b: getattr(dynamics, name)(*b, *shared)
    if vmapped:
        fn = jax.vmap(fn, in_axes=-1, out_axes=-1)
    return fn(*batched)


def split(y):
    """`(body, controller)` -> positions, velocities (each `(body, controller continuous)`)
    and the discrete controller state."""
    body, control = y
    continuous = control.continuous
    positions = (body.positions, None if continuous is None else continuous[0])
    velocities = (body.velocities, None if continuous is None else continuous[1])
    return positions, velocities, control.discrete


def join(positions, velocities, discrete):
    """The inverse of `split`."""
    body = BodyState(positions[0], velocities[0])
    continuous = None if positions[1] is None else (positions[1], velocities[1])
    return body, ControllerState(discrete, continuous)


def materialise(tree):
    """`tree`, its floating leaves computed here rather than fused into their consumers.

    XLA's CPU compiler never fuses through a matrix product, and removes
    `lax.optimization_barrier`; each leaf is therefore passed through a product with a 2x2
    identity (exact: `1 * x` plus an exact zero; with a 1x1 identity XLA turns the product
    into a fusible multiply)."""

    def one(x):
        if not jnp.issubdtype(jnp.result_type(x), jnp.floating):
            return x
        flat = jnp.stack([x.reshape(-1), jnp.zeros_like(x.reshape(-1))])
        eye = jnp.eye(2, dtype=flat.dtype)
        kept = jnp.dot(eye, flat, precision=jax.lax.Precision.HIGHEST)
        return kept[0].reshape(x.shape)

    return jax.tree_util.tree_map(one, tree)


def computed_here(a):
    """`a` (at least 1-D) computed where it stands rather than fused into each of its
    consumers, by a product with the identity over its leading axis (exact: `1 x` plus
    exact zeros; values meet only the values of the same trailing index, so of the same
    controller in the batch-last layout). For backward passes: there XLA fused a
    residual's dynamic slice, or a cotangent's arithmetic, into every consumer, and
    computed it again in each (a pair table's loop ran ten times slower). Cheaper than
    `materialise` for large arrays: no padded copy."""
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    return jax.lax.dot_general(
        eye, a, (((1,), (0,)), ((), ())), precision=jax.lax.Precision.HIGHEST
    )


def axpy(h, dx, x):
    """`x + h dx` on matching pytrees."""
    return jax.tree_util.tree_map(lambda a, b: b + h * a, dx, x)


def zeros_like_tree(tree):
    return jax.tree_util.tree_map(jnp.zeros_like, tree)

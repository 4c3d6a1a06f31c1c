"""Gradient refinement of controllers through the simulation, with optax."""

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from .._control.base import AbstractController
from .._sim import execution
from .._sim.simulate import time_grid
from .._task import Task, _differentiable_fitness, _timing
from .history import History


class Smoothing(eqx.Module):
    """How to smooth the discrete switches of a task so that its fitness has useful gradients.

    - `regime_width`: seconds over which a controller's discrete switches are blended (for
        `Regimes`, the cross-fade between neighbouring regimes; see `Regimes.blend`).
    - `friction_velocity`: if given and larger than the world's, the friction law's
        regularisation speed (m/s) on the smoothed problem: the stick-slip switch is
        spread over a wider band of sliding speeds.

    `Smoothing()` (both off) is exactly the problem the user asked for. Fitness is always
    reported on that problem; only gradients are taken on the smoothed one.
    """

    regime_width: float = eqx.field(default=0.0, static=True)
    friction_velocity: float | None = eqx.field(default=None, static=True)

    def __post_init__(self):
        if not (isinstance(self.regime_width, int | float) and self.regime_width >= 0):
            raise ValueError(
                f"Smoothing.regime_width = {self.regime_width!r}; allowed: a number >= 0 (s)"
            )
        v = self.friction_velocity
        if v is not None and not (isinstance(v, int | float) and v > 0):
            raise ValueError(
                f"Smoothing.friction_velocity = {v!r}; allowed: None or a number > 0 (m/s)"
            )

    def task(self, task: Task) -> Task:
        """The task with its world's friction smoothed."""
        if self.friction_velocity is None:
            return task
        world = task.world
        wider = max(float(world.friction_velocity), float(self.friction_velocity))
        smoother = eqx.tree_at(lambda w: w.friction_velocity, world, wider)
        return eqx.tree_at(lambda t: t.world, task, smoother)

    def controllers(self, params: AbstractController) -> AbstractController:
        """The controllers with their switches blended."""
        return params if self.regime_width == 0 else params.smoothed(self.regime_width)

    def annealed(self, stages: int = 4) -> tuple["Smoothing", ...]:
        """A schedule for `refine`: `stages` smoothings from this one down to none, in equal
        steps (the friction's speed down to the world's own, which `task` never goes
        below). Each stage compiles its own gradient, so a few stages, not one per step."""
        if isinstance(stages, bool) or not isinstance(stages, int) or stages < 2:
            raise ValueError(f"Smoothing.annealed stages = {stages!r}; allowed: an integer >= 2")
        last = stages - 1
        v = self.friction_velocity
        return tuple(
            Smoothing(
                regime_width=self.regime_width * (last - k) / last,
                friction_velocity=None if v is None or k == last else v * (last - k) / last,
            )
            for k in range(stages)
        )


@dataclass(frozen=True)
class RefineHistory(History):
    """`History` of a refinement (the true fitness of every controller at every step, in
    the searches' format), plus how many gradients came back non-finite and were skipped."""

    nonfinite_gradients: int = field(default=0)


@dataclass(frozen=True)
class RefineResult:
    """What `refine` returns besides the controllers.

    - `fitness`: the true fitness of the returned controllers.
    - `history`: a `RefineHistory`.
    """

    fitness: np.ndarray
    history: RefineHistory


def _local_value_and_grad(task: Task, trainable, frozen, smoothing: Smoothing, gradient_from):
    def total(p):
        params = eqx.combine(p, frozen)
        fitness = _differentiable_fitness(
            smoothing.task(task), smoothing.controllers(params), gradient_from
        )
        # Each controller's fitness depends on its own parameters only, so the gradient of the
        # sum is every controller's own gradient. A blown-up run (-inf) contributes nothing
        # here and gets a non-finite gradient of its own, which `refine` skips.
        return jnp.sum(jnp.where(jnp.isfinite(fitness), fitness, 0.0)), fitness

    (_, fitness), grads = jax.value_and_grad(total, has_aux=True)(trainable)
    return fitness, grads


def _local_gradients(args, params):
    task, spec, smoothing, gradient_from = args
    trainable, frozen = eqx.partition(params, spec)
    return _local_value_and_grad(task, trainable, frozen, smoothing, gradient_from)


def _value_and_grad(task: Task, params, spec, smoothing: Smoothing, gradient_from=None):
    """Smoothed fitness and its gradient for every controller (leading batch axis), laid
    out as `Task.evaluate` lays out a batch (in parts, one per device, each whole lane
    groups), through the simulation's reverse-mode layout (`simulate_batch(...,
    reverse_mode=True)`: a scan of checkpointed save intervals); `gradient_from` (s) holds
    the motion before it constant."""
    return execution.run(_local_gradients, (task, spec, smoothing, gradient_from), params)


def _gradient_from(task: Task, final_phase) -> float | None:
    """The time the gradient starts from for `final_phase` seconds at the end (rounded to
    the task's save intervals), `None` for the whole motion."""
    if final_phase is None:
        return None
    duration = float(task.duration)
    if (
        isinstance(final_phase, bool)
        or not isinstance(final_phase, int | float)
        or not 0 < final_phase <= duration
    ):
        raise ValueError(
            f"refine final_phase = {final_phase!r}; allowed: None or seconds > 0 and <= the "
            f"task's duration {duration:g}"
        )
    save_dt = time_grid(task.duration, **_timing(task)).save_dt
    held = max(0, round((duration - final_phase) / save_dt))
    return None if held == 0 else held * save_dt


@eqx.filter_jit
def _update(optimizer, space, spec, params, grads, opt_state, fitness, best, best_fitness):
    """One projected ascent step for every controller whose gradient is finite; the others
    keep their parameters and optimizer state. Also tracks each controller's best."""
    trainable, frozen = eqx.partition(params, spec)
    leaves = jax.tree_util.tree_leaves(grads)
    ok = jnp.ones(fitness.shape, dtype=bool)
    for g in leaves:
        ok = ok & jnp.all(jnp.isfinite(g.reshape(g.shape[0], -1)), axis=1)
    ok = ok & jnp.isfinite(fitness)
    ascent = jax.tree_util.tree_map(lambda g: -jnp.where(jnp.isfinite(g), g, 0.0), grads)
    updates, new_state = jax.vmap(optimizer.update)(ascent, opt_state, trainable)
    stepped = eqx.combine(optax.apply_updates(trainable, updates), frozen)
    stepped = jax.vmap(space.project)(stepped)

    new_params = jax.tree_util.tree_map(lambda n, o: _select(ok, n, o), stepped, params)
    new_state = jax.tree_util.tree_map(
        lambda n, o: _select(ok, n, o) if eqx.is_array(n) and n.ndim else n,
        new_state,
        opt_state,
    )
    best, best_fitness = _keep_better(params, fitness, best, best_fitness)
    return new_params, new_state, best, best_fitness, jnp.sum(~ok)


def _keep_better(params, fitness, best, best_fitness):
    """Each controller's best version so far, and its fitness."""
    better = fitness > best_fitness
    best = jax.tree_util.tree_map(lambda p, b: _select(better, p, b), params, best)
    return best, jnp.maximum(fitness, best_fitness)


def _select(mask, new, old):
    """Per controller (leading axis), `new` where `mask` holds, else `old`."""
    return jnp.where(mask.reshape(mask.shape + (1,) * (new.ndim - 1)), new, old)


def fitness_and_gradient(
    task: Task,
    params: AbstractController,
    *,
    smoothing: Smoothing | None = None,
    final_phase: float | None = None,
) -> tuple[Float[Array, " batch"], AbstractController]:
    """The fitness of a batch of controllers on the problem smoothed by `smoothing`, and its
    gradient with respect to each controller's trainable leaves (the others are `None`),
    through the whole fixed-step simulation, or with `final_phase` (seconds) only through
    its last part: the motion before it is held where it is (see `refine`). A blown-up run
    has fitness `-inf` and a non-finite gradient."""
    smoothing = Smoothing() if smoothing is None else smoothing
    gradient_from = _gradient_from(task, final_phase)
    params, spec = _prepared(task, params)
    return _value_and_grad(task, params, spec, smoothing, gradient_from)


def _prepared(task: Task, params):
    """The batch placed as `Task.evaluate` places it, and the family's trainable spec."""
    execution.batch_size(params)
    params = execution.placed(params)
    return params, task.space.trainable(jax.tree_util.tree_map(lambda a: a[0], params))


def refine(
    task: Task,
    params: AbstractController,
    optimizer: optax.GradientTransformation,
    steps: int,
    *,
    smoothing: Smoothing | Sequence[Smoothing] | None = None,
    final_phase: float | None = None,
    callback: Callable[[int, AbstractController, np.ndarray], None] | None = None,
) -> tuple[AbstractController, RefineResult]:
    """Gradient ascent on the continuous parameters of a batch of controllers.

    Every controller (leading batch axis) is refined independently, all in one compiled
    call per step: the gradient of its fitness is taken through the whole simulation (the
    fixed-step solver, differentiated by diffrax with checkpointing), on the problem
    smoothed by `smoothing`, and `optimizer` (any optax transformation, applied to each
    controller separately) turns it into an ascent step. Only the leaves the family marks
    `trainable` change (for `Regimes`: regime times and reflex coefficients; reflex numbers
    and the period stay), and after each step the family's `project` puts them back within
    bounds (clipping: the bounds are part of the problem, and the paper's coefficient
    distribution puts much of its mass right at them, where a reparametrisation such as
    tanh would have vanishing gradients).

    A controller whose gradient comes back non-finite (a blown-up run) is not updated at
    that step; `result.history.nonfinite_gradients` counts these.

    **Arguments:**

    - `task`: what to optimise (fitness is maximised).
    - `params`: the starting controllers, stacked along a leading axis.
    - `optimizer`: e.g. `optax.adam(1e-2)`.
    - `steps`: gradient steps.
    - `smoothing`: see `Smoothing`; the default (`None`) is no smoothing. A sequence of
        them is a schedule: the steps are shared among them in order, as evenly as
        possible (`Smoothing(...).annealed()` anneals to none: early steps see a smooth
        landscape, the last ones the problem as posed).
    - `final_phase`: if given (seconds), gradients flow only through the last
        `final_phase` seconds of each motion (rounded to save intervals): what happens
        before is held as it is (truncated backpropagation: cheaper, and free of the
        chaotic long-horizon contact a whole-motion gradient goes through; for example to
        land a somersault upright). The fitness is still the whole motion's.
    - `callback`: called after every step with the step number, the updated controllers
        and the true fitness of the controllers that step started from.

    **Returns:** `(best, result)`: every controller's best version seen (by true fitness,
    the starting point included) and a `RefineResult`. The history holds the true fitness of
    all controllers at every step, `steps + 1` rows of the batch (step 0 is the start).
    """
    schedule = _schedule(smoothing, steps)
    gradient_from = _gradient_from(task, final_phase)
    params, spec = _prepared(task, params)
    opt_state = jax.vmap(optimizer.init)(eqx.filter(params, spec))
    best = params
    best_fitness = jnp.full(execution.batch_size(params), -jnp.inf)
    parts, skipped = [], 0
    for k in range(steps):
        _, grads = _value_and_grad(task, params, spec, schedule[k], gradient_from)
        # The true fitness from `evaluate` itself, even unsmoothed: the gradient program
        # computes the same function, but XLA fuses its forward pass differently (it keeps
        # what the backward pass needs), so its values can differ in the last bits, and the
        # controllers returned must re-evaluate to exactly the fitness recorded for them.
        fitness = task.evaluate(params)
        parts.append(History(np.asarray(fitness), np.full(fitness.shape[0], k)))
        params, opt_state, best, best_fitness, bad = _update(
            optimizer, task.space, spec, params, grads, opt_state, fitness, best, best_fitness
        )
        skipped += int(bad)
        if callback is not None:
            callback(k + 1, params, np.asarray(fitness))
    # The controllers after the last step need their fitness only, not another gradient.
    fitness = task.evaluate(params)
    parts.append(History(np.asarray(fitness), np.full(fitness.shape[0], steps)))
    best, best_fitness = _keep_better(params, fitness, best, best_fitness)
    history = History.concatenate(parts)
    return best, RefineResult(
        fitness=np.asarray(best_fitness),
        history=RefineHistory(history.fitness, history.step, nonfinite_gradients=skipped),
    )


def _schedule(smoothing, steps: int) -> list[Smoothing]:
    """The smoothing of each of `steps` steps."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        raise ValueError(f"refine steps = {steps!r}; allowed: an integer >= 0")
    if smoothing is None or isinstance(smoothing, Smoothing):
        return [Smoothing() if smoothing is None else smoothing] * steps
    stages = list(smoothing)
    if not stages or not all(isinstance(s, Smoothing) for s in stages):
        raise ValueError(
            f"refine smoothing = {smoothing!r}; allowed: None, a Smoothing or a non-empty "
            f"sequence of them (a schedule)"
        )
    # Stage i covers steps [i * steps // n, (i + 1) * steps // n).
    return [stages[k * len(stages) // steps] for k in range(steps)] if steps else []


def gradient_cost(
    task: Task,
    params: AbstractController,
    smoothing: Smoothing | None = None,
    final_phase: float | None = None,
):
    """How many simulations one gradient step costs, measured: the median wall time of the
    forward-and-backward pass over a batch divided by that of `task.evaluate` on it (both
    compiled first, three calls each). `refine` also evaluates the true fitness each step unless the
    smoothing is off; add 1 for that."""
    import time

    smoothing = Smoothing() if smoothing is None else smoothing
    gradient_from = _gradient_from(task, final_phase)
    params, spec = _prepared(task, params)

    def timed(fn, repeats=3):
        jax.block_until_ready(fn())  # compile
        runs = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(fn())
            runs.append(time.perf_counter() - start)
        return sorted(runs)[repeats // 2]  # the median: one slow call must not decide it

    grad_s = timed(lambda: _value_and_grad(task, params, spec, smoothing, gradient_from))
    eval_s = timed(lambda: task.evaluate(params))
    return max(1.0, grad_s / eval_s)


__all__ = [
    "RefineHistory",
    "RefineResult",
    "Smoothing",
    "fitness_and_gradient",
    "gradient_cost",
    "refine",
]

"""`Task`: body, world, controller family, objective and simulation settings, and the one hot
function `task.evaluate`."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, Float, PRNGKeyArray

from ._body.base import AbstractBody, BodyState
from ._control.base import AbstractController, AbstractControllerSpace
from ._objective.registry import Objective
from ._sim import execution
from ._sim.compile import simulation_jit
from ._sim.robust import Robustness
from ._sim.simulate import SolverName, simulate, simulate_batch, time_grid
from ._sim.trajectory import SimulationState, Trajectory
from ._world import World


class Task(eqx.Module):
    """What to synthesise: a body in a world, a controller family to search, an objective
    to maximise and how to simulate.

    **Arguments:**

    - `body`: the character (e.g. `jaxmotion.lattices.cube()`).
    - `world`: gravity, floor, contact and friction.
    - `space`: the controller family searched (e.g. `RegimesSpace(num_regimes=4, t_per=1.0)`).
    - `objective`: the fitness, **maximised** (e.g. `Objective({"forward": 1, "upright": -10})`).
    - `duration`: simulated time per evaluation, s.
    - `dt`: physics step of the fixed-step search solver, s.
    - `save_dt`: interval between the samples the objective sees, s (default: up to 20 ms,
        dividing the duration: 50 per second is plenty for the objectives, and observing
        costs a share of every evaluation). Never changes the motion.
    - `control_dt`: the controllers' control period, s (default `dt`: a tick every step).
    - `initial_state`: the body's state at the start of every evaluation (default: its rest
        pose, at rest), e.g. `trajectory.final.body` to search for a motion that starts
        where another ended (each controller starts from its own initial state, at time 0).
    - `robustness`: a `Robustness` to evaluate every controller from several random starts
        around `initial_state` and score it by their mean (or worst) fitness, so a search
        finds controllers that work from wherever they start (the second paper's robust
        controllers); `evaluate` then needs a key. Default `None`: one start.
    - `second_dt`: a second, shorter physics step (a whole fraction of the control period
        `control_dt`, default `dt`; e.g. `dt / 2`): `evaluate` also simulates every
        controller with it and scores it by the lower of the two fitnesses, so a search
        keeps only motions that do not depend on the step (a contact-rich motion found at
        one step can be an artefact of it, and fall apart under accurate integration; see
        the README's "Motions that survive accurate physics"). It costs the second
        simulation (`dt / second_dt` times the first). Default `None`: one step.

    **Raises:** `ValueError` for non-positive or inconsistent times, or an initial state
    that is not the body's, before any compilation.
    """

    body: AbstractBody
    world: World
    space: AbstractControllerSpace
    objective: Objective
    duration: float = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    save_dt: float | None = eqx.field(static=True)
    control_dt: float | None = eqx.field(static=True)
    initial_state: BodyState | None
    robustness: Robustness | None
    second_dt: float | None = eqx.field(static=True)

    def __init__(
        self,
        body: AbstractBody,
        world: World,
        space: AbstractControllerSpace,
        objective: Objective,
        duration: float,
        dt: float = 1e-3,
        save_dt: float | None = None,
        *,
        control_dt: float | None = None,
        initial_state: BodyState | None = None,
        robustness: Robustness | None = None,
        second_dt: float | None = None,
    ):
        if robustness is not None and not isinstance(robustness, Robustness):
            raise TypeError(
                f"Task.robustness must be a Robustness or None; got {type(robustness).__name__}"
            )
        for name, value, kind in (
            ("body", body, AbstractBody),
            ("world", world, World),
            ("space", space, AbstractControllerSpace),
            ("objective", objective, Objective),
        ):
            if not isinstance(value, kind):
                raise TypeError(
                    f"Task.{name} must be a {kind.__name__}; got {type(value).__name__}"
                )
        time_grid(duration, dt, save_dt, control_dt)  # raises ValueError naming a bad time
        if second_dt is not None:
            _check_second_dt(duration, dt, save_dt, control_dt, second_dt)
        self.body = body
        self.world = world
        self.space = space
        self.objective = objective
        self.duration = float(duration)
        self.dt = float(dt)
        self.save_dt = None if save_dt is None else float(save_dt)
        self.control_dt = None if control_dt is None else float(control_dt)
        self.initial_state = None if initial_state is None else _body_state(body, initial_state)
        self.robustness = robustness
        self.second_dt = None if second_dt is None else float(second_dt)

    def sample(self, num: int, *, key: PRNGKeyArray) -> AbstractController:
        """`num` random controllers of the task's family, stacked along a leading axis."""
        return jax.vmap(lambda k: self.space.sample(key=k))(jr.split(key, num))

    def evaluate(
        self,
        params: AbstractController,
        *,
        chunk: int | None = None,
        key: PRNGKeyArray | None = None,
    ) -> Float[Array, " batch"]:
        """Fitness (maximised) of a batch of controllers (leading batch axis on every array).

        One compiled program simulates the batch, split into one part per CPU device JAX
        sees, the parts run side by side (`jaxmotion.use_cpu_cores`); it is compiled once
        per body structure, controller family and padded part size (each part is padded to
        whole groups of 8, at least 16: batches of 1 to 16 share one compilation), and
        reused by every later call with the same shapes (`chunk`: evaluate in calls of this
        many controllers, the last padded, to reuse the compilation of that size). A run that
        blows up gets fitness `-inf` (the worst) rather than raising or returning NaN;
        count them with `jnp.isneginf(fitness)`.

        Results are bitwise reproducible: the same batch gives the same fitness every time,
        whatever the number of devices, and a controller's fitness depends neither on its
        place in the batch nor on the size of the batch it comes in (so a search's best
        controller replays alone to the very fitness the search recorded), with one
        exception measured so far: for the 2D figures and Rex, parts of a batch of 176 to 264
        controllers and more (calls of 350-530 and more on two devices) may round differently
        (the README's "Known problem: wide parts of some figures"). Batches under 16
        are padded to 16, which is why they cost about as much as 16.

        With `robustness`, every controller is simulated from `robustness.samples` random
        starts drawn from `key` (one key for the batch, or one per controller, `(batch,)`:
        controllers with the same key see the same starts, `random_starts`) and scored by
        the mean or the worst of their fitness (a start that blows up scores `-inf`, and
        so does the controller). The same keys give the same fitness. Without
        `robustness`, `key` is not used.

        With `second_dt`, the fitness is the lower of the fitness at `dt` and at
        `second_dt` (each as above, from the same starts).
        """
        if self.second_dt is not None:
            first = _one_step(self).evaluate(params, chunk=chunk, key=key)
            return jnp.minimum(first, self._at_second_dt().evaluate(params, chunk=chunk, key=key))
        if self.robustness is not None:
            return self._robust(params, chunk, key, sensed=False)
        return execution.run(_fitness, self, params, chunk=chunk)

    def evaluate_sensed(
        self,
        params: AbstractController,
        *,
        chunk: int | None = None,
        key: PRNGKeyArray | None = None,
    ) -> tuple[Float[Array, " batch"], Float[Array, "batch num_saves num_senses"]]:
        """`evaluate`, and the senses each controller perceived at the saved times
        (`AbstractController.perceive`): what a mutation with the second paper's relevance
        heuristic looks at. The fitness is bitwise `evaluate`'s. With `robustness`, the
        senses are those of the first random start; with `second_dt`, those at `dt`."""
        if self.second_dt is not None:
            first, senses = _one_step(self).evaluate_sensed(params, chunk=chunk, key=key)
            second = self._at_second_dt().evaluate(params, chunk=chunk, key=key)
            return jnp.minimum(first, second), senses
        if self.robustness is not None:
            return self._robust(params, chunk, key, sensed=True)
        return execution.run(_fitness_and_senses, self, params, chunk=chunk)

    def _at_second_dt(self) -> "Task":
        """This task at its second step (the same control period), with no second step."""
        return dataclasses.replace(
            self, dt=self.second_dt, control_dt=self.control_dt or self.dt, second_dt=None
        )

    def random_starts(self, key: PRNGKeyArray, batch: int | None = None) -> BodyState:
        """The starts `evaluate` simulates from with `robustness` (`Robustness.starts`
        around the task's initial state): for one key, body states along a leading axis of
        `robustness.samples`; with `batch`, axes `(batch, samples)` (`key` one key, or one
        per controller)."""
        if self.robustness is None:
            raise ValueError("this task has no robustness: every evaluation starts alike")
        start = self.body.initial_state() if self.initial_state is None else self.initial_state
        out = _starts(self.robustness, self.body, start, _batch_keys(key, batch))
        return _first(out) if batch is None and jnp.ndim(key) == 0 else out

    def _robust(self, params, chunk, key, sensed: bool):
        if key is None:
            raise ValueError(
                "this task evaluates every controller from random starts (Task.robustness): "
                "evaluate needs key=..., one PRNG key or one per controller"
            )
        starts = self.random_starts(key, execution.batch_size(params))
        fitness, senses = [], None
        for k in range(self.robustness.samples):
            start = jax.tree_util.tree_map(lambda a, k=k: a[:, k], starts)
            if sensed and k == 0:
                f, senses = execution.run(
                    _fitness_and_senses_from, self, (params, start), chunk=chunk
                )
            else:
                f = execution.run(_fitness_from, self, (params, start), chunk=chunk)
            fitness.append(f)
        score = self.robustness.reduced(jnp.stack(fitness, axis=-1))
        return (score, senses) if sensed else score

    def trajectories(
        self,
        params: AbstractController,
        *,
        senses: bool = False,
        initial_state=None,
        positions: bool = False,
    ) -> Trajectory:
        """The trajectories behind `evaluate`, with a leading batch axis (`senses`: with
        `Trajectory.senses`; `positions`: with `Trajectory.positions`). `initial_state`: a
        body state to start every controller from instead of the task's, or a batch of
        `SimulationState`s (`trajectories.final`) to continue each controller from its
        own."""
        execution.batch_size(params)
        task = self if initial_state is None else _starting(self, initial_state)
        if isinstance(initial_state, SimulationState):
            # Each controller continues from its own state: the states are batched with it.
            if positions:
                return execution.run(_continued_posed, (task, senses), (params, initial_state))
            return execution.run(_continued, (task, senses), (params, initial_state))
        if positions:
            return execution.run(_posed_trajectories, (task, senses), params)
        fn = _sensed_trajectories if senses else _trajectories
        return execution.run(fn, task, params)

    def simulate(
        self,
        params: AbstractController,
        *,
        solver: SolverName = "symplectic",
        dt: float | None = None,
        save_dt: float | None = None,
        initial_state=None,
        rtol: float | None = None,
        atol: float | None = None,
        positions: bool = False,
    ) -> Trajectory:
        """Simulate one controller (playback) with the search settings, unless `solver`,
        `dt` or `save_dt` say otherwise (`solver="tsit5"` for an adaptive check).
        `positions`: also keep the body's positions state at the saved times
        (`Trajectory.positions`, what `jaxmotion.export` needs).

        With the search's own fixed-step solver the trajectory is computed exactly as
        `evaluate` computes it, so a controller replays to the very fitness the search
        recorded (contact-rich motions are chaotic: a different rounding anywhere would
        grow into a visibly different motion); `save_dt` only chooses which states are
        sampled. `initial_state`: a body state to start from instead of the task's, or a
        `SimulationState` (`trajectory.final`) to continue this controller from it exactly.
        """
        dt = self.dt if dt is None else dt
        save_dt = self.save_dt if save_dt is None else save_dt
        task = dataclasses.replace(self, dt=dt, save_dt=save_dt, second_dt=None)
        if solver == "symplectic":
            one = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], params)
            if isinstance(initial_state, SimulationState):
                state = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], initial_state)
                out = task.trajectories(one, initial_state=state, positions=positions)
            else:
                out = task.trajectories(one, initial_state=initial_state, positions=positions)
            return jax.tree_util.tree_map(lambda a: a[0], out)
        start = initial_state if initial_state is not None else task.initial_state
        return _simulate_one(task, params, solver, start, rtol, atol, positions)

    def fitness(self, trajectory: Trajectory) -> Float[Array, "..."]:
        """The objective of one trajectory, or of a batch of them (leading axis)."""
        if trajectory.com.ndim == 3:
            return jax.vmap(self.objective)(trajectory)
        return self.objective(trajectory)


def _body_state(body: AbstractBody, state) -> BodyState:
    """`state` as the body's `BodyState`, checked against the body's own layout."""
    try:
        state = BodyState(*state)
    except TypeError:
        raise ValueError(
            f"initial_state must be a body state (positions, velocities), e.g. "
            f"body.state(...) or trajectory.final.body; got {type(state).__name__}"
        ) from None
    reference = body.initial_state()
    ref_struct = jax.tree_util.tree_structure(reference)
    if jax.tree_util.tree_structure(state) != ref_struct:
        raise ValueError(
            f"initial_state does not have the layout of the body's states "
            f"({ref_struct}); make it with body.state(...)"
        )
    for a, b in zip(
        jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(reference), strict=True
    ):
        if jnp.shape(a) != jnp.shape(b):
            raise ValueError(
                f"initial_state has a part of shape {jnp.shape(a)} where the body's states "
                f"have {jnp.shape(b)} (one body's state, no batch axis)"
            )
    return state


def _one_step(task: Task) -> Task:
    """The task without its second step."""
    return dataclasses.replace(task, second_dt=None)


def _check_second_dt(duration, dt, save_dt, control_dt, second_dt) -> None:
    control = dt if control_dt is None else control_dt
    if isinstance(second_dt, bool) or not isinstance(second_dt, int | float) or second_dt <= 0:
        raise ValueError(f"second_dt = {second_dt!r}; allowed: a number of seconds > 0")
    if second_dt >= dt:
        raise ValueError(
            f"second_dt = {second_dt!r} is not shorter than dt = {dt!r}; allowed: a shorter "
            f"step that divides the control period {control!r} (e.g. {dt / 2!r})"
        )
    try:
        time_grid(duration, second_dt, save_dt, control)
    except ValueError as e:
        raise ValueError(
            f"second_dt = {second_dt!r} does not fit the control period {control!r}: {e}"
        ) from e


def _starting(task: Task, initial_state) -> Task:
    """The task with another body state to start from (a `SimulationState` is handled by
    the caller)."""
    if initial_state is None or isinstance(initial_state, SimulationState):
        return task
    return eqx.tree_at(
        lambda t: t.initial_state,
        task,
        _body_state(task.body, initial_state),
        is_leaf=lambda x: x is None,
    )


def _timing(task: Task) -> dict:
    """The task's simulation settings, as `simulate` takes them."""
    return dict(dt=task.dt, save_dt=task.save_dt, control_dt=task.control_dt)


def _local(
    task: Task,
    params,
    *,
    senses: bool = False,
    initial_state=None,
    positions: bool = False,
    reverse_mode: bool = False,
    gradient_from: float | None = None,
) -> Trajectory:
    start = task.initial_state if initial_state is None else initial_state
    return simulate_batch(
        task.body,
        params,
        task.world,
        task.duration,
        initial_state=start,
        record_senses=senses,
        record_positions=positions,
        reverse_mode=reverse_mode,
        gradient_from=gradient_from,
        **_timing(task),
    )


def _objective(task: Task, trajectories: Trajectory):
    return jax.vmap(task.objective)(trajectories)


def _fitness(task: Task, params):
    return _objective(task, _local(task, params))


def _differentiable_fitness(task: Task, params, gradient_from: float | None = None):
    """`_fitness` in the layout built for reverse-mode differentiation (before
    `gradient_from` seconds, held constant)."""
    return _objective(task, _local(task, params, reverse_mode=True, gradient_from=gradient_from))


def _fitness_and_senses(task: Task, params):
    trajectories = _local(task, params, senses=True)
    return _objective(task, trajectories), trajectories.senses


def _fitness_from(task: Task, batch):
    params, start = batch
    return _objective(task, _local(task, params, initial_state=start))


def _fitness_and_senses_from(task: Task, batch):
    params, start = batch
    trajectories = _local(task, params, senses=True, initial_state=start)
    return _objective(task, trajectories), trajectories.senses


def _batch_keys(key, batch: int | None):
    """`(batch,)` keys: the given ones, or one key repeated (`batch` None: one)."""
    if jnp.ndim(key) == 0:
        return jnp.stack([key] * (1 if batch is None else batch))
    if batch is not None and key.shape != (batch,):
        raise ValueError(
            f"evaluate's key has shape {key.shape}; allowed: one key, or one per controller "
            f"({batch},)"
        )
    return key


def _first(tree):
    return jax.tree_util.tree_map(lambda a: a[0], tree)


@eqx.filter_jit
def _starts(robustness: Robustness, body, start, keys):
    return jax.vmap(lambda k: robustness.starts(body, start, k))(keys)


def _trajectories(task: Task, params) -> Trajectory:
    return _local(task, params)


def _sensed_trajectories(task: Task, params) -> Trajectory:
    return _local(task, params, senses=True)


def _continued(args, batch) -> Trajectory:
    (task, senses), (params, state) = args, batch
    return _local(task, params, senses=senses, initial_state=state)


def _posed_trajectories(args, params) -> Trajectory:
    task, senses = args
    return _local(task, params, senses=senses, positions=True)


def _continued_posed(args, batch) -> Trajectory:
    (task, senses), (params, state) = args, batch
    return _local(task, params, senses=senses, initial_state=state, positions=True)


@simulation_jit
def _simulate_one(
    task: Task, params, solver, initial_state, rtol, atol, positions=False
) -> Trajectory:
    return simulate(
        task.body,
        params,
        task.world,
        task.duration,
        solver=solver,
        initial_state=initial_state,
        rtol=rtol,
        atol=atol,
        positions=positions,
        **_timing(task),
    )

"""`Composite`: a composite motion to tune (the second paper's section 3): controllers run one
after another on one body, scored by a script, with the transition-point search."""

from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ._body.base import AbstractBody, BodyState
from ._control.base import AbstractController
from ._control.sequence import Sequence
from ._objective.script import Script
from ._search.transitions import TransitionSearchResult, transition_search
from ._sim import execution
from ._sim.simulate import SolverName, simulate, simulate_batch, time_grid
from ._sim.trajectory import Trajectory
from ._world import World


class Composite(eqx.Module):
    """A composite motion: named controllers run in turn on one body (a `Sequence`), scored
    by a composite-motion script (`Script`, the second paper's Table 4) whose phases are the
    controllers' names; what is tuned is when each controller hands over to the next.

    **Arguments:**

    - `body`, `world`: the character and its world.
    - `controllers`: the phases in order, a mapping of names to controllers (`{"cartwheel":
        ..., "jump": ..., "shuffle": ...}`); the script's phases are these names.
    - `script`: the script's text (or a `Script` with these phases and tick).
    - `duration`: the whole motion's length, s.
    - `dt`, `control_dt`: the simulation's step and the controllers' control period, s
        (`control_dt` defaults to `dt`).
    - `tick`: the script's unit of time, s (its `delta_time` counts ticks; transitions fall
        on ticks): a whole number of control periods that divides the duration (default:
        the control period). A tick longer than the control period lets controllers act
        every step while a script counts coarser ticks, as the paper's Table 4 does.
    - `initial_state`: the body's state at the start (default: the rest pose).

    Samples are saved at every tick, so the script reads each phase exactly from its first
    tick to its last.

    **Raises:** `ValueError` (or `ScriptError`) for a bad time, no controllers, a name that
    is not an identifier, or a script that does not parse, before anything compiles.
    """

    body: AbstractBody
    world: World
    controllers: tuple[AbstractController, ...]
    script: Script
    duration: float = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    control_dt: float = eqx.field(static=True)
    tick: float = eqx.field(static=True)
    initial_state: BodyState | None

    def __init__(
        self,
        body: AbstractBody,
        world: World,
        controllers: Mapping[str, AbstractController],
        script: str | Script,
        duration: float,
        dt: float = 1e-3,
        *,
        control_dt: float | None = None,
        tick: float | None = None,
        initial_state: BodyState | None = None,
    ):
        if not isinstance(controllers, Mapping) or not controllers:
            raise ValueError(
                "Composite.controllers must be a non-empty mapping of phase names to "
                f"controllers; got {controllers!r}"
            )
        grid = time_grid(duration, dt, None, control_dt)
        tick = _tick(tick, grid.control_dt, duration)
        names = tuple(controllers)
        if isinstance(script, Script):
            if script.phases != names or script.tick != tick:
                raise ValueError(
                    f"Composite.script has phases {script.phases} and tick {script.tick}; "
                    f"allowed: the controllers' names {names} and the tick {tick}"
                )
        else:
            script = Script(script, names, tick)
        Sequence(tuple(controllers.values()), np.zeros(len(names) - 1))  # checks them
        self.body = body
        self.world = world
        self.controllers = tuple(controllers.values())
        self.script = script
        self.duration = float(duration)
        self.dt = float(dt)
        self.control_dt = grid.control_dt
        self.tick = tick
        self.initial_state = initial_state

    @property
    def phases(self) -> tuple[str, ...]:
        return self.script.phases

    def equally_spaced(self) -> np.ndarray:
        """The paper's default transitions: the phases share the duration equally (on the
        tick grid)."""
        k = len(self.controllers)
        ticks = np.round(np.arange(1, k) * self.duration / k / self.tick)
        return ticks * self.tick

    def sequence(self, transitions: Float[ArrayLike, " K-1"]) -> Sequence:
        """The controllers as one `Sequence` switching at `transitions` (s)."""
        return Sequence(self.controllers, transitions)

    def evaluate(self, transitions: Float[ArrayLike, "arrays K-1"]) -> Float[Array, " arrays"]:
        """The script's `total` for each transition array, simulated in one call (a
        blown-up run scores `-inf`)."""
        transitions = jnp.asarray(transitions, dtype=float)
        if transitions.ndim != 2 or transitions.shape[1] != len(self.controllers) - 1:
            raise ValueError(
                f"transitions have shape {transitions.shape}; allowed: (arrays, "
                f"{len(self.controllers) - 1})"
            )
        return execution.run(_fitness, self, _sequences(self.controllers, transitions))

    def trajectory(
        self,
        transitions: Float[ArrayLike, " K-1"],
        *,
        solver: SolverName = "symplectic",
        positions: bool = False,
    ) -> Trajectory:
        """The motion with these transitions (the search's own simulation with the
        default solver; `positions`: also save the body's positions, for export)."""
        transitions = jnp.asarray(transitions, dtype=float)
        if solver == "symplectic" and not positions:
            one = _sequences(self.controllers, transitions[None])
            out = execution.run(_trajectories, self, one)
            return jax.tree_util.tree_map(lambda a: a[0], out)
        return simulate(
            self.body,
            self.sequence(transitions),
            self.world,
            self.duration,
            dt=self.dt,
            save_dt=self.tick,
            control_dt=self.control_dt,
            solver=solver,
            initial_state=self.initial_state,
            positions=positions,
        )

    def values(self, transitions: Float[ArrayLike, " K-1"]) -> dict[str, float]:
        """Every value the script assigns (its per-phase credits and `total`) for these
        transitions."""
        trajectory = self.trajectory(transitions)
        values = self.script.values(trajectory, jnp.asarray(transitions, dtype=float))
        return {name: float(v) for name, v in values.items()}

    def search(
        self,
        *,
        key: PRNGKeyArray,
        initial: Float[ArrayLike, " K-1"] | None = None,
        num_arrays: int = 16,
        rounds: int = 16,
        mutations: int = 4,
        callback=None,
        state=None,
        history=None,
    ) -> TransitionSearchResult:
        """The transition-point search (second paper, Figure 5; see `transition_search`)
        from `initial` (default: equally spaced), on the tick grid; `state` and `history`
        continue a search from a round's state (`callback(round, state)`) and the history
        up to it."""
        return transition_search(
            self,
            self.duration,
            key=key,
            initial=self.equally_spaced() if initial is None else initial,
            num_arrays=num_arrays,
            rounds=rounds,
            mutations=mutations,
            tick=self.tick,
            callback=callback,
            state=state,
            history=history,
        )


def _tick(tick, control_dt: float, duration: float) -> float:
    """The script's tick: a whole number of control periods dividing the duration."""
    if tick is None:
        return control_dt
    if isinstance(tick, bool) or not isinstance(tick, (int, float)) or not tick > 0:
        raise ValueError(f"tick = {tick!r}; allowed: a number of seconds > 0")
    for name, value, unit in (("tick", tick, control_dt), ("duration", duration, tick)):
        n = round(value / unit)
        if n < 1 or abs(value - n * unit) > 1e-6 * unit:
            raise ValueError(
                f"{name} = {value!r} is not a whole number of "
                f"{'control periods' if name == 'tick' else 'ticks'} ({unit!r} s); allowed: "
                f"e.g. {max(n, 1) * unit:.6g}"
            )
    return round(tick / control_dt) * control_dt


def _sequences(controllers, transitions) -> Sequence:
    """A batch of sequences (leading axis), one per transition array."""
    template = Sequence(controllers, np.zeros(len(controllers) - 1))
    return jax.vmap(lambda t: eqx.tree_at(lambda s: s.transitions, template, t))(transitions)


def _simulated(composite: Composite, sequences) -> Trajectory:
    return simulate_batch(
        composite.body,
        sequences,
        composite.world,
        composite.duration,
        dt=composite.dt,
        save_dt=composite.tick,
        control_dt=composite.control_dt,
        initial_state=composite.initial_state,
    )


def _fitness(composite: Composite, sequences):
    trajectories = _simulated(composite, sequences)
    return jax.vmap(composite.script)(trajectories, sequences.transitions)


def _trajectories(composite: Composite, sequences) -> Trajectory:
    return _simulated(composite, sequences)


__all__ = ["Composite"]

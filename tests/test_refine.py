"""Gradient refinement: gradients through the simulation agree with finite differences,
smoothing of width zero is the problem as posed, refinement improves, and blown-up runs are
skipped and counted."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest

import jaxmotion as jm

# Central differences in float64 with this step agree with the gradient to rounding and
# O(step^2); over 0.3 s of contact-rich motion, this relative tolerance leaves room for the
# growth of rounding differences.
FD_STEP = 1e-6
FD_RTOL = 1e-4
# Length of the ascent step (in parameter space) that must improve the smoothed objective.
ASCENT_STEP = 1e-5
SMOOTH = jm.Smoothing(regime_width=0.05, friction_velocity=0.1)

# The terms the configs use, in three objectives (one gradient compilation each): the
# translation terms, the rotation terms (weights spreading their gradients' scales, so that
# an error in any one would show), and every piecewise-constant term (contacts, hops,
# upright, fallen), whose gradient must be zero, as their differences are.
TERMS = {
    "translation": {"forward": 1.0, "max_height": 0.7, "distance": 0.3},
    "rotation": {
        "backflip": {"term": "rotation", "axis": "left", "weight": 1.0},
        "roll": {"term": "rotation", "axis": "forward", "absolute": True, "weight": 0.6},
        "net_yaw": 0.8,
        "final_tilt": 0.4,
    },
    "piecewise": {
        "contact_time": 1.0,
        "upright": 1.0,
        "on_ground_at_end": 1.0,
        "hops": 1.0,
        "fallen": 1.0,
        "min_contacts": 1.0,
    },
}


def task_for(weights, duration=0.3):
    return jm.Task(
        jm.lattices.cube(),
        jm.World(gravity=2.5),
        jm.RegimesSpace(4, 0.2),
        jm.Objective(weights),
        duration=duration,
    )


def _assert_central_differences(grad, params, fitness, fields=("times", "coefficients")):
    """`grad` against central differences of `fitness` (a batch's fitness) in every
    coordinate of the trainable `fields` (by default those of `Regimes`)."""
    for field in fields:
        g = np.asarray(getattr(grad, field))
        base = np.asarray(getattr(params, field))
        for c in range(base.shape[1]):
            step = np.zeros_like(base)
            step[:, c] = FD_STEP
            up = fitness(eqx.tree_at(lambda p, f=field: getattr(p, f), params, base + step))
            down = fitness(eqx.tree_at(lambda p, f=field: getattr(p, f), params, base - step))
            fd = (up - down) / (2 * FD_STEP)
            scale = max(1.0, float(np.max(np.abs(g))))
            np.testing.assert_allclose(g[:, c], fd, rtol=FD_RTOL, atol=FD_RTOL * scale)


# The rotation objective differentiates the same simulation as the translation one (the
# gradients of `rotation` and `final_tilt` themselves are checked against differences in
# test_objectives.py); one more gradient compile: `-m slow`.
@pytest.mark.parametrize(
    "term", [pytest.param(t, marks=pytest.mark.slow) if t == "rotation" else t for t in TERMS]
)
def test_gradients_agree_with_central_differences(term, x64):
    task = task_for(TERMS[term])
    params = task.sample(3, key=jr.key(4))
    _, grad = jm.fitness_and_gradient(task, params, smoothing=SMOOTH)

    def fitness(p):
        return np.asarray(jm.fitness_and_gradient(task, p, smoothing=SMOOTH)[0])

    _assert_central_differences(grad, params, fitness)
    assert grad.reflexes is None and grad.t_per is None  # discrete and fixed: not trained


# The gradient program computes the same function as `evaluate`, but XLA fuses its forward
# pass differently (it keeps what the backward pass needs), so the values agree to rounding
# (float64 here) rather than bitwise; any smoothing at all moves them by orders of magnitude
# more.
POSED_ATOL = 1e-9
# The tests below differentiate the translation objective of the finite-difference test,
# in float64, smoothed by SMOOTH, with 16 controllers or fewer: one gradient compilation
# for all of them (the problem as posed adds one).
SHARED = TERMS["translation"]


def test_width_zero_is_the_problem_as_posed(x64):
    task = task_for(SHARED)
    params = task.sample(16, key=jr.key(1))
    fitness, _ = jm.fitness_and_gradient(task, params, smoothing=jm.Smoothing())
    posed = np.asarray(task.evaluate(params))
    np.testing.assert_allclose(np.asarray(fitness), posed, rtol=0, atol=POSED_ATOL)
    smoothed, _ = jm.fitness_and_gradient(task, params, smoothing=SMOOTH)
    assert np.max(np.abs(np.asarray(smoothed) - posed)) > 100 * POSED_ATOL  # smoothing acts


def test_refine_improves_the_smoothed_objective_from_a_fixed_start(x64):
    task = task_for(SHARED)
    start = task.sample(16, key=jr.key(0))
    before, grad = jm.fitness_and_gradient(task, start, smoothing=SMOOTH)
    # A short projected step along the gradient raises the smoothed objective of every
    # controller with a clear gradient (some lie still on the floor and have none). Short:
    # contact makes the objective rough, and longer steps can overshoot it.
    norm = np.sqrt(
        np.sum(np.asarray(grad.times) ** 2, axis=1)
        + np.sum(np.asarray(grad.coefficients) ** 2, axis=1)
    )
    unit = ASCENT_STEP / np.maximum(norm, 1e-12)[:, None]
    moved = eqx.tree_at(
        lambda p: (p.times, p.coefficients),
        start,
        (start.times + unit * grad.times, start.coefficients + unit * grad.coefficients),
    )
    after, _ = jm.fitness_and_gradient(task, jax.vmap(task.space.project)(moved), smoothing=SMOOTH)
    has_gradient = norm > 0.1
    assert has_gradient.sum() >= 4
    assert np.all(np.asarray(after)[has_gradient] > np.asarray(before)[has_gradient])
    # refine with Adam raises the best true fitness of the batch, and returns each
    # controller's best version with the fitness its history recorded.
    best, result = jm.refine(task, start, optax.adam(0.02), 8, smoothing=SMOOTH)
    history = result.history.fitness.reshape(9, 16)
    assert len(result.history) == 9 * 16
    assert result.fitness.max() > history[0].max()
    np.testing.assert_array_equal(result.fitness, history.max(axis=0))
    np.testing.assert_array_equal(np.asarray(task.evaluate(best)), result.fitness)


def test_final_phase_gradient_is_the_gradient_of_the_held_motion(x64):
    """`final_phase = h` differentiates the fitness of the motion whose first `T - h`
    seconds are those of the given controllers, held, and whose rest is simulated by the
    controllers varied, from where the held part ended: checked against central
    differences of exactly that, built from a simulation and its continuation."""
    from jaxmotion._sim.simulate import simulate_batch

    task = task_for(SHARED)  # 0.3 s, samples every 20 ms
    held, phase = 0.2, 0.1
    params = task.sample(3, key=jr.key(5))
    _, grad = jm.fitness_and_gradient(task, params, smoothing=SMOOTH, final_phase=phase)
    world = SMOOTH.task(task).world
    blended = jax.vmap(SMOOTH.controllers)
    early = simulate_batch(task.body, blended(params), world, held)

    def fitness(p):
        late = simulate_batch(task.body, blended(p), world, phase, initial_state=early.final)
        whole = jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b[:, 1:]], axis=1),
            (early.ts, early.points, early.com, early.frame, early.contact),
            (late.ts, late.points, late.com, late.frame, late.contact),
        )
        trajectory = jm.Trajectory(*whole, finite=early.finite & late.finite, final=late.final)
        return np.asarray(jax.vmap(task.objective)(trajectory))

    _assert_central_differences(grad, params, fitness)
    # The whole motion as the final phase is the whole gradient.
    _, whole = jm.fitness_and_gradient(task, params, smoothing=SMOOTH, final_phase=0.3)
    _, plain = jm.fitness_and_gradient(task, params, smoothing=SMOOTH)
    np.testing.assert_array_equal(np.asarray(whole.coefficients), np.asarray(plain.coefficients))
    assert not np.allclose(np.asarray(grad.coefficients), np.asarray(plain.coefficients))


def test_smoothing_schedules():
    smooth = jm.Smoothing(regime_width=0.06, friction_velocity=0.3)
    assert smooth.annealed(3) == (
        smooth,
        jm.Smoothing(regime_width=0.03, friction_velocity=0.15),
        jm.Smoothing(),
    )
    from jaxmotion._search.refine import _schedule

    stages = smooth.annealed(3)
    assert _schedule(stages, 5) == [stages[0], stages[0], stages[1], stages[1], stages[2]]
    assert _schedule(smooth, 2) == [smooth, smooth]
    for bad in ([], [smooth, 0.1]):
        with pytest.raises(ValueError, match="allowed: None, a Smoothing or a non-empty"):
            _schedule(bad, 3)
    with pytest.raises(ValueError, match="stages = 1; allowed: an integer >= 2"):
        smooth.annealed(1)
    task = task_for(SHARED)
    for bad in (0.0, 0.5, True):
        with pytest.raises(ValueError, match=r"final_phase = .*; allowed: None or seconds > 0"):
            jm.refine(task, task.sample(2, key=jr.key(0)), optax.adam(0.1), 1, final_phase=bad)


def test_nonfinite_gradients_are_skipped_and_counted(x64):
    task = task_for(SHARED)
    params = task.sample(4, key=jr.key(2))
    broken = eqx.tree_at(lambda p: p.coefficients, params, params.coefficients.at[0].set(jnp.nan))
    best, result = jm.refine(task, broken, optax.adam(0.05), 3, smoothing=SMOOTH)
    assert result.history.nonfinite_gradients == 3  # controller 0, at each of the 3 steps
    assert np.all(np.isneginf(result.history.fitness.reshape(4, 4)[:, 0]))
    assert np.all(np.isfinite(np.asarray(best.coefficients[1:])))
    assert np.all(np.isnan(np.asarray(best.coefficients[0])))  # untouched, never updated
    assert np.all(np.isfinite(result.fitness[1:]))


def test_compare_writes_a_table_and_a_plot_on_equal_budgets(tmp_path):
    import csv
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    # The default experiment over 1 s instead of 5 (the gradients' share of the test's time).
    config = tmp_path / "short.toml"
    config.write_text(
        (root / "configs" / "default.toml").read_text().replace("duration = 5.0", "duration = 1.0")
    )
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxmotion",
            "compare",
            str(config),
            "--evaluations",
            "200",
            "--batch",
            "50",
            "--seeds",
            "0,1",
            "--top-k",
            "2",
            "--strategies",
            "plain,final",
            "--final-phase",
            "0.5",
            "--gradient-cost",
            "9",  # so that the 100 simulations left after the search buy exactly 5 steps
            "--out",
            str(tmp_path),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    folder = Path(done.stdout.strip().splitlines()[-1])
    assert {p.name for p in folder.iterdir()} == {
        "compare.csv",
        "compare.md",
        "compare.png",
        "summary.json",
    }
    rows = list(csv.DictReader((folder / "compare.csv").open()))
    assert len(rows) == 6
    for seed in ("0", "1"):
        alone, refined, final = (r for r in rows if r["seed"] == seed)
        assert alone["method"] == "search" and refined["method"] == "search+refine"
        assert final["method"] == "search+refine final 0.5s"
        for row in (refined, final):
            assert int(row["gradient_steps"]) == 5  # 100 / (2 controllers x (9 + 1))
            assert int(row["simulations"]) == int(alone["simulations"]) == 100 + 200
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["gradient_cost_simulations"] == 9
    assert set(summary["strategies"]) == {"plain", "final"}
    # Refinement returns the best version it saw, its start included.
    for strategy in summary["strategies"].values():
        assert all(b >= a for a, b in zip(summary["start_best"], strategy["best"], strict=True))
    assert "| stochastic search |" in (folder / "compare.md").read_text()


def test_torque_limited_figure_gradients_agree_with_central_differences(x64):
    """The snake with joints weak enough to clip (5 N m) on the floor, driven by spring
    nets, 0.3 s: the gradient of the configs' fitness through the torque-limited dynamics
    (clip, floor forces as generalised forces, the joint-space solve) against central
    differences in every spring constant and initial position."""
    figure = jm.figures.snake(max_torque=5.0)
    task = jm.Task(
        figure,
        jm.World(),
        jm.SpringNetSpace(figure, tau=0.03),
        jm.Objective({"distance": 1.0, "max_height": 0.5}),
        duration=0.3,
        dt=0.001,
        control_dt=0.005,
    )
    params = task.sample(2, key=jr.key(1))
    _, grad = jm.fitness_and_gradient(task, params, smoothing=SMOOTH)

    def fitness(p):
        return np.asarray(jm.fitness_and_gradient(task, p, smoothing=SMOOTH)[0])

    fields = ("stiffness", "positions")
    assert all(np.max(np.abs(np.asarray(getattr(grad, f)))) > 0 for f in fields)  # they move it
    _assert_central_differences(grad, params, fitness, fields)

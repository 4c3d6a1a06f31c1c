"""`Task.evaluate`: agreement with the plain simulation, batch invariance, failures,
compilation reuse and sharding over devices."""

import json
import logging
import os
import subprocess
import sys
import textwrap

import jax
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm


def cube_task(duration=1.0, dt=1e-3, body=None, **kw):
    return jm.Task(
        body or jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 0.5),
        jm.Objective({"forward": 1.0, "upright": -10.0, "max_height": 0.5}),
        duration=duration,
        dt=dt,
        **kw,
    )


def test_evaluate_equals_the_objective_of_each_simulation(x64):
    task = cube_task()
    params = task.sample(6, key=jr.key(0))
    fitness = np.asarray(task.evaluate(params))
    for b in range(6):
        one = jax.tree_util.tree_map(lambda a, b=b: a[b], params)
        trajectory = jm.simulate(task.body, one, task.world, task.duration, dt=task.dt)
        assert fitness[b] == pytest.approx(float(task.objective(trajectory)), abs=1e-9)


# 32 (several lane groups) runs the same code as 5 at another shape (CI's time): `-m slow`.
@pytest.mark.parametrize("size", [5, pytest.param(32, marks=pytest.mark.slow)])
def test_fitness_does_not_depend_on_batch_order(size):
    task = cube_task()
    params = task.sample(size, key=jr.key(1))
    fitness = np.asarray(task.evaluate(params))
    order = np.random.default_rng(0).permutation(size)
    shuffled = jax.tree_util.tree_map(lambda a: a[order], params)
    np.testing.assert_array_equal(np.asarray(task.evaluate(shuffled)), fitness[order])
    np.testing.assert_array_equal(np.asarray(task.evaluate(params)), fitness)  # deterministic


def test_fitness_does_not_depend_on_the_batch_it_comes_in():
    """Bitwise: any slice of a batch, down to a single controller, scores the same."""
    task = cube_task()
    params = task.sample(48, key=jr.key(1))
    fitness = np.asarray(task.evaluate(params))
    for lo, hi in [(0, 16), (16, 48), (5, 30), (7, 8), (40, 45)]:
        part = jax.tree_util.tree_map(lambda a, lo=lo, hi=hi: a[lo:hi], params)
        np.testing.assert_array_equal(np.asarray(task.evaluate(part)), fitness[lo:hi])


def _figure_task(figure):
    return jm.Task(
        figure,
        jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1),
        jm.TimeBSRSpace(figure, num_rules=4, t_per=0.5, tau_min=0.05, tau_max=0.25),
        jm.Objective({"forward": 1.0, "rotations": 0.5}),
        duration=1.0,
        dt=0.005,
    )


@pytest.mark.parametrize(
    ("make", "widths"),
    [
        (lambda: cube_task(body=jm.lattices.pyramid()), (40, 64)),
        # The chair runs the lattices' code as the pyramid does (CI's time): `-m slow`.
        pytest.param(lambda: cube_task(body=jm.lattices.chair()), (40,), marks=pytest.mark.slow),
        # Rex compiles for a minute at two widths (CI's time): `-m slow`. Star-Man's sense-based
        # controllers are checked alone and in a batch of 20 in test_closed_loop.py.
        pytest.param(lambda: _figure_task(jm.figures.rex()), (24,), marks=pytest.mark.slow),
    ],
    ids=["pyramid", "chair", "rex"],
)
def test_every_body_scores_a_controller_bitwise_the_same_at_every_batch_width(make, widths):
    """Wider batches compile to other loop layouts (and, with XLA's YNNPACK fusions, other
    groupings of the same sums: the pyramid differed from 40 controllers on, Rex from 24
    with the classic loop emitters); a controller's fitness must not notice, or a search's
    best would replay alone to another fitness than the search recorded."""
    task = make()
    params = task.sample(max(widths), key=jr.key(4))
    part = lambda lo, hi: jax.tree_util.tree_map(lambda a: a[lo:hi], params)
    # Each controller in a batch of 16 (the width a lone replay is padded to), and alone.
    blocks = np.concatenate(
        [np.asarray(task.evaluate(part(lo, lo + 16))) for lo in range(0, max(widths), 16)]
    )
    assert float(task.evaluate(part(0, 1))[0]) == blocks[0]
    for width in widths:
        np.testing.assert_array_equal(
            np.asarray(task.evaluate(part(0, width))), blocks[:width], err_msg=f"{width=}"
        )


def test_blown_up_runs_score_worst_and_do_not_poison_the_batch():
    stiff = cube_task(dt=5e-3, body=jm.lattices.cube(stiffness=5e6))
    fitness = np.asarray(stiff.evaluate(stiff.sample(4, key=jr.key(2))))
    assert np.all(np.isneginf(fitness))
    assert not np.any(np.isnan(fitness))
    ok = cube_task()
    assert np.all(np.isfinite(np.asarray(ok.evaluate(ok.sample(4, key=jr.key(2))))))


def test_evaluate_compiles_once_per_shape_and_is_reused(caplog):
    task = cube_task(duration=0.5)
    params = task.sample(8, key=jr.key(3))
    task.evaluate(params).block_until_ready()  # may compile
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        task.evaluate(task.sample(8, key=jr.key(4))).block_until_ready()
        # A new Task with the same shapes (another search) reuses the compiled call too.
        other = cube_task(duration=0.5)
        other.evaluate(params).block_until_ready()
    compiled = [r.getMessage() for r in caplog.records if "_evaluate" in r.getMessage()]
    assert compiled == []


def test_task_rejects_bad_settings_before_compiling():
    with pytest.raises(ValueError, match=r"duration = -2.0; allowed: a number of seconds > 0"):
        cube_task(duration=-2.0)
    with pytest.raises(TypeError, match=r"Task.objective must be a Objective"):
        jm.Task(jm.lattices.cube(), jm.World(), jm.RegimesSpace(), {"forward": 1.0}, 1.0)
    with pytest.raises(ValueError, match=r"leading batch axis"):
        cube_task().evaluate(jm.RegimesSpace(4, 0.5).sample(key=jr.key(0)))


def test_trajectories_and_simulate_playback_match_evaluate():
    task = cube_task()
    params = task.sample(3, key=jr.key(5))
    fitness = np.asarray(task.evaluate(params))
    trajectories = task.trajectories(params)
    np.testing.assert_array_equal(np.asarray(task.fitness(trajectories)), fitness)
    one = jax.tree_util.tree_map(lambda a: a[0], params)
    # Playback computes exactly what evaluate computed: the same fitness to the last bit.
    assert float(task.fitness(task.simulate(one))) == fitness[0]
    adaptive = task.simulate(one, solver="tsit5")
    assert bool(adaptive.finite)


SHARDING_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax, jax.random as jr, numpy as np
    import jaxmotion as jm
    task = jm.Task(jm.lattices.cube(), jm.World(), jm.RegimesSpace(4, 0.5),
                   jm.Objective({"forward": 1.0, "upright": -10.0}), duration=0.5)
    out = {"devices": len(jax.devices())}
    # 41 controllers: padded and split in two on two devices, whole on one (a batch too
    # small to split runs the one-device program on either).
    params = task.sample(41, key=jr.key(9))
    out[41] = np.asarray(task.evaluate(params)).tolist()
    # A sense-based 3D figure with filtered senses (Bob's controller family): sharded over
    # two devices, its program rounded differently from the one-device program, and places
    # past the first 256 of a device's share differently again.
    bob = jm.figures.bob()
    world = jm.World(floor_stiffness=3.0e4, floor_damping=300.0, friction_velocity=0.1)
    space = jm.SenseBSRSpace(bob, num_rules=10, tau_min=0.05, filter_time=0.05)
    task = jm.Task(bob, world, space, jm.Objective({"forward": 1.0}), duration=0.3, dt=0.005)
    params = task.sample(40, key=jr.key(3))
    out["bob"] = np.asarray(task.evaluate(params)).tolist()
    copies = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[7:8], 40, axis=0), params)
    out["bob_copies"] = np.asarray(task.evaluate(copies)).tolist()
    print(json.dumps(out))
    """
)


def run_with_devices(n):
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={n}")
    out = subprocess.run(
        [sys.executable, "-c", SHARDING_SCRIPT], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_two_devices_give_the_one_device_results_bitwise():
    """A batch split over two CPU devices scores every controller exactly as one device
    does, and a controller copied to every place of a split batch scores the same at each."""
    one, two = run_with_devices(1), run_with_devices(2)
    assert (one["devices"], two["devices"]) == (1, 2)
    assert one["41"] == two["41"]
    assert one["bob"] == two["bob"]
    assert len(set(one["bob"])) > 1  # the controllers differ, and so do their motions
    for out in (one, two):
        assert out["bob_copies"] == [out["bob"][7]] * 40


def test_simulation_compiler_options_are_kept_only_if_xla_knows_them(monkeypatch):
    """The simulations compile with the preferred XLA options; an option this XLA does not
    know (a later XLA may drop one) is left out instead of failing every compile."""
    from jaxmotion._sim import compile as compilation

    compilation.compiler_options.cache_clear()
    try:
        assert compilation.compiler_options() == compilation._PREFERRED
        compilation.compiler_options.cache_clear()
        monkeypatch.setattr(compilation, "_PREFERRED", {"xla_cpu_no_such_option": False})
        assert compilation.compiler_options() == {}
    finally:
        compilation.compiler_options.cache_clear()

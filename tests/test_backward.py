"""The reverse-mode path of the simulation: the hand-written derivatives of the hot loops
agree with JAX's own, the layout built for `jax.grad` computes the same motion as the
search's, and a gradient split over two devices equals the one-device gradient."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion._body.lattice import _spring_forces
from jaxmotion._control.regimes import _mix, _pick_among
from jaxmotion._sim.simulate import simulate_batch

# In float64 the written derivatives and JAX's differ only by the order of their sums:
# rounding, a few units in the 15th digit.
VJP_RTOL = 1e-11


def _symmetric(rng, n, batch, low, high):
    a = rng.uniform(low, high, size=(n, n, *batch))
    return jnp.asarray((a + np.swapaxes(a, 0, 1)) / 2)


def _assert_same_vjp(fn, args, cotangent, body=None):
    """`fn`'s custom VJP against the VJP JAX derives from its body (`fn.fun` unless
    given)."""
    out, written = jax.vjp(fn, *args)
    reference_out, derived = jax.vjp(fn.fun if body is None else body, *args)
    jax.tree_util.tree_map(
        lambda a, b: np.testing.assert_allclose(a, b, rtol=VJP_RTOL, atol=0), out, reference_out
    )
    for a, b in zip(written(cotangent), derived(cotangent), strict=True):
        if b is None or jnp.issubdtype(jnp.result_type(b), jax.dtypes.float0):
            continue  # an integer input (the regime index) has no cotangent
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(a, b, rtol=VJP_RTOL, atol=VJP_RTOL * scale)


@pytest.mark.parametrize("batch", [(), (5,)], ids=["one", "batch-last"])
def test_spring_force_derivative_is_the_derivative(batch, x64):
    """Every input's cotangent, for a lattice's symmetric tables (the written derivative
    uses their symmetry), one body or a batch along the last axis; the tables' own
    singleton batch axes (the lattice's constants) are summed over."""
    rng = np.random.default_rng(0)
    n = 6
    x = jnp.asarray(rng.normal(size=(3, n, *batch)))
    v = jnp.asarray(rng.normal(size=(3, n, *batch)))
    rest = _symmetric(rng, n, batch, 0.5, 1.5)
    own = (1,) * len(batch)
    stiffness = _symmetric(rng, n, own, 0.0, 2.0)
    damping = _symmetric(rng, n, own, 0.0, 1.0)
    no_spring = _symmetric(rng, n, own, 0.0, 1.0)
    g = tuple(jnp.asarray(rng.normal(size=(n, *batch))) for _ in range(3))
    _assert_same_vjp(_spring_forces, (x, v, rest, stiffness, damping, no_spring), g)


@pytest.mark.parametrize("batch", [(), (5,)], ids=["one", "batch-last"])
def test_regime_table_derivatives_are_the_derivatives(batch, x64):
    rng = np.random.default_rng(1)
    regimes, n = 4, 3
    plan = jnp.asarray(rng.normal(size=(regimes, n, n, *batch)))
    cotangent = jnp.asarray(rng.normal(size=(n, n, *batch)))
    index = jnp.asarray(rng.integers(0, regimes, size=batch))
    _assert_same_vjp(
        lambda p, i: _pick_among(regimes, p, i),
        (plan, index),
        cotangent,
        body=lambda p, i: _pick_among.fun(regimes, p, i),
    )
    weights = jnp.asarray(rng.uniform(0.0, 1.0, size=(regimes, *batch)))
    _assert_same_vjp(_mix, (plan, weights), cotangent)


# The two layouts differ by XLA's fusion of the same float64 arithmetic: rounding, grown
# over 0.3 s of contact.
LAYOUT_ATOL = 1e-9


def test_reverse_mode_layout_computes_the_same_motion(x64):
    body, world = jm.lattices.cube(), jm.World(gravity=2.5)
    space = jm.RegimesSpace(4, 0.2)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(3), 4))
    run = lambda reverse: simulate_batch(body, controllers, world, 0.3, reverse_mode=reverse)
    plain, reverse = run(False), run(True)
    for a, b in zip(
        jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(reverse), strict=True
    ):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=LAYOUT_ATOL)
    with pytest.raises(ValueError, match="reverse_mode=True needs solver='symplectic'"):
        simulate_batch(body, controllers, world, 0.3, solver="tsit5", reverse_mode=True)


SHARDED_GRADIENT = textwrap.dedent(
    """
    import json
    import jax, jax.random as jr, numpy as np
    import jaxmotion as jm
    task = jm.Task(jm.lattices.cube(), jm.World(), jm.RegimesSpace(4, 0.5),
                   jm.Objective({"forward": 1.0, "upright": -10.0}), duration=0.5)
    # 41 controllers: split in two on two devices, whole on one.
    params = task.sample(41, key=jr.key(9))
    smoothing = jm.Smoothing(regime_width=0.05, friction_velocity=0.1)
    fitness, grad = jm.fitness_and_gradient(task, params, smoothing=smoothing)
    print(json.dumps({"devices": len(jax.devices()), "fitness": np.asarray(fitness).tolist(),
                      "times": np.asarray(grad.times).tolist(),
                      "coefficients": np.asarray(grad.coefficients).tolist()}))
    """
)


def _gradient_on(devices):
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
    out = subprocess.run(
        [sys.executable, "-c", SHARDED_GRADIENT],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


# Each device's share is padded to other widths on one and on two devices (48 against 24
# per device here), and XLA's backward loops group some float32 sums by width: the
# gradients agree to rounding of their sums over the ticks, not bitwise (the fitness does).
SHARDED_RTOL = 1e-5


def test_gradient_over_two_devices_equals_the_one_device_gradient():
    one, two = _gradient_on(1), _gradient_on(2)
    assert (one["devices"], two["devices"]) == (1, 2)
    assert one["fitness"] == two["fitness"]
    for key in ("times", "coefficients"):
        a, b = np.asarray(one[key]), np.asarray(two[key])
        np.testing.assert_allclose(b, a, rtol=SHARDED_RTOL, atol=SHARDED_RTOL * np.abs(a).max())

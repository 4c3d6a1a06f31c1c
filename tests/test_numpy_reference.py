"""jaxmotion's simulation against an independent NumPy implementation of the same model
(`benchmarks/numpy_model.py`: sparse springs gathered and scattered by index, where jaxmotion
uses dense pair tables), in float64."""

import sys
from pathlib import Path

import jax
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import numpy_model

WORLDS = {
    "isotropic": jm.World(),
    "anisotropic": jm.World(friction_direction=(-1.0, 0.5), friction_preferred=1.7),
    "low gravity": jm.World(gravity=2.0, friction=0.4),
}


@pytest.mark.parametrize("world", list(WORLDS))
# The chair is the same model on another topology (three more compilations): `-m slow`.
@pytest.mark.parametrize(
    "builder", [jm.lattices.cube, pytest.param(jm.lattices.chair, marks=pytest.mark.slow)]
)
def test_agrees_with_the_numpy_model(builder, world, x64):
    task = jm.Task(
        builder(),
        WORLDS[world],
        jm.RegimesSpace(4, 0.3),
        jm.Objective({"forward": 1.0}),
        # Long enough for contact, impacts and regime switches (the lattice must move, see
        # below), short enough to end before a stick phase amplifies rounding: in deep
        # contact the regularised friction acts as a drag mu * Fn / friction_velocity that is
        # stiffer than the explicit 1 ms step can follow, and there the two implementations'
        # last-bit differences grew from 1e-15 to 1e-8 within 60 ms (chair, anisotropic,
        # t = 0.54 s).
        duration=0.5,
    )
    params = task.sample(6, key=jr.key(3))
    ours = np.asarray(
        jax.vmap(lambda c: jm.simulate(task.body, c, task.world, task.duration))(params).points[
            :, -1
        ]
    )
    theirs = numpy_model.simulate(numpy_model.prepare(task, params, np.float64))
    theirs = np.transpose(theirs, (2, 1, 0))  # (3, n, B) -> (B, n, 3)
    assert (
        np.abs(ours - np.asarray(jax.tree_util.tree_map(lambda a: a, task.body.points))).max()
        > 0.01
    )
    np.testing.assert_allclose(ours, theirs, atol=1e-10)  # NUMPY_AGREEMENT: rounding only

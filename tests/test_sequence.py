"""`Sequence`: controllers concatenated in time (the second paper's composite motion): the
same motion as the controllers run one after another from the carried state, batched over
transition arrays, saved and loaded with the results."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion.experiment import controller_from_dict, controller_to_dict

WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)
DT = 4e-3
PHASE = 0.32  # s: every phase lasts 0 or this, so the references need few compilations
LAYOUTS = 1e-4  # m: the unbatched and batch-last layouts round differently in the last bits


@pytest.fixture(scope="module")
def star_man():
    body = jm.figures.star_man()
    time_space = jm.TimeBSRSpace(body, num_rules=4, t_per=0.3, tau_min=0.02, tau_max=0.2)
    sense_space = jm.SenseBSRSpace(body, num_rules=6, tau_min=0.02, tau_max=0.2, filter_time=0.02)
    # A time-based controller, a sense-based one (with a filter), a time-based one again:
    # t_per = 0.3 s does not divide the phases' starts, so a controller that saw the
    # global time rather than its local time would act differently.
    controllers = [
        time_space.sample(key=jr.key(0)),
        sense_space.sample(key=jr.key(1)),
        time_space.sample(key=jr.key(2)),
    ]
    return body, time_space, controllers


def task_for(body, space, duration, initial_state=None):
    return jm.Task(
        body,
        WORLD,
        space,
        jm.Objective({"forward": 1.0}),
        duration=duration,
        dt=DT,
        save_dt=DT,
        initial_state=initial_state,
    )


def one_after_another(body, space, controllers, transitions, duration):
    """The reference: controller k simulated alone from where controller k - 1 left the
    body, for its phase's length; the parts joined."""
    bounds = [0.0, *transitions, duration]
    parts, start = [], None
    for k, c in enumerate(controllers):
        length = round(bounds[k + 1] - bounds[k], 9)
        if length == 0:
            continue  # a phase of no length: the controller never acts
        part = task_for(body, space, length, initial_state=start).simulate(c)
        parts.append(part)
        start = part.final.body
    return np.concatenate(
        [np.asarray(parts[0].points)] + [np.asarray(p.points)[1:] for p in parts[1:]]
    )


def test_a_batch_of_sequences_is_its_controllers_one_after_another_bitwise(star_man):
    """Each transition array of a batch, simulated in one call, computes bitwise what its
    controllers compute run one after another, each started afresh (its own initial state,
    local time 0) from the body state the previous one left: with a phase skipped (equal
    transitions), a phase starting at time 0 and one starting at the end."""
    body, space, controllers = star_man
    duration = 2 * PHASE
    transitions = np.array([[PHASE, PHASE], [0.0, PHASE], [PHASE, 2 * PHASE]])
    seq = jm.Sequence(controllers, transitions[0])
    batch = jax.vmap(lambda tr: eqx.tree_at(lambda s: s.transitions, seq, tr))(
        jnp.asarray(transitions)
    )
    task = task_for(body, space, duration)
    out = task.trajectories(batch)
    assert bool(jnp.all(out.finite))
    # The phase in charge at the end (a transition at the end is never reached).
    np.testing.assert_array_equal(out.final.controller.discrete.phase, [2, 2, 1])
    for i, tr in enumerate(transitions):
        ref = one_after_another(body, space, controllers, list(tr), duration)
        np.testing.assert_array_equal(np.asarray(out.points[i]), ref, err_msg=f"transitions {tr}")


def test_one_sequence_alone_moves_as_in_a_batch(star_man):
    """`jaxmotion.simulate` of one sequence (the unbatched layout, scalar phases) switches
    where the batch does and moves alike, to the rounding in which the two layouts differ
    (chaotic contact amplifies it, so only over a short motion)."""
    body, space, controllers = star_man
    duration = 2 * PHASE
    seq = jm.Sequence(controllers[1:], [PHASE])
    alone = jm.simulate(body, seq, WORLD, duration, dt=DT, save_dt=DT)
    batch = task_for(body, space, duration).simulate(seq)
    assert int(alone.final.controller.discrete.phase) == 1
    np.testing.assert_allclose(alone.points, batch.points, atol=LAYOUTS)


def test_reads_senses_only_when_a_controller_does(star_man):
    _, _, (time_a, sense_b, time_c) = star_man
    assert not jm.Sequence([time_a, time_c], [0.5]).reads_senses
    assert jm.Sequence([time_a, sense_b], [0.5]).reads_senses


def test_json_round_trip_keeps_every_controller(star_man):
    """`best_controller.json` holds a sequence as its controllers' own descriptions and its
    transitions; loading gives the same controllers (families, values) and transitions."""
    _, _, controllers = star_man
    seq = jm.Sequence(controllers, [0.25, 0.5])
    data = json.loads(json.dumps(controller_to_dict(seq)))
    assert data["family"] == "sequence"
    assert [c["family"] for c in data["params"]["controllers"]] == [
        "time_bsr",
        "sense_bsr",
        "time_bsr",
    ]
    back = controller_from_dict(data)
    assert isinstance(back, jm.Sequence)
    for a, b in zip(jax.tree_util.tree_leaves(seq), jax.tree_util.tree_leaves(back), strict=True):
        np.testing.assert_array_equal(a, b)
    assert [type(c) for c in back.controllers] == [type(c) for c in controllers]
    assert back.controllers[1].filter_time == controllers[1].filter_time


@pytest.mark.parametrize(
    "transitions, match",
    [
        ([0.5], r"shape \(1,\); allowed: \(2,\)"),
        ([0.5, 0.25], "not ascending"),
        ([-0.1, 0.2], "finite times >= 0"),
        ([0.1, float("nan")], "finite times >= 0"),
    ],
)
def test_bad_transitions_are_refused_naming_them(star_man, transitions, match):
    _, _, controllers = star_man
    with pytest.raises(ValueError, match=match):
        jm.Sequence(controllers, transitions)


def test_bad_controllers_are_refused(star_man):
    _, _, controllers = star_man
    with pytest.raises(ValueError, match="at least one controller"):
        jm.Sequence([], [])
    with pytest.raises(TypeError, match=r"controllers\[1\] must be a controller"):
        jm.Sequence([controllers[0], "jump"], [0.5])
    with pytest.raises(ValueError, match="unknown parameters"):
        controller_from_dict({"family": "sequence", "params": {"controllers": [], "phases": 2}})


def test_the_control_period_is_the_simulations(star_man):
    """A sequence counts ticks, so it needs the simulation's control period: `prepare`
    without it says how to get it; the simulation sets it."""
    body, _, controllers = star_man
    seq = jm.Sequence(controllers, [0.25, 0.5])
    with pytest.raises(ValueError, match="control_dt is not set"):
        seq.prepare(body)
    assert seq.on_grid(DT).control_dt == DT
    assert all(c is d for c, d in zip(seq.on_grid(DT).controllers, controllers, strict=True))

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxmotion as jm

BUILDERS = [jm.lattices.cube, jm.lattices.pyramid, jm.lattices.chair]


def test_cube_has_8_masses_and_28_springs_of_three_kinds():
    cube = jm.lattices.cube(size=2.0)
    assert cube.num_masses == 8
    assert cube.num_springs == 28
    lengths = np.asarray(cube.rest_lengths)
    # 12 edges, 12 face diagonals, 4 body diagonals, in that order.
    np.testing.assert_allclose(lengths[:12], 2.0, rtol=1e-6)
    np.testing.assert_allclose(lengths[12:24], 2.0 * np.sqrt(2), rtol=1e-6)
    np.testing.assert_allclose(lengths[24:], 2.0 * np.sqrt(3), rtol=1e-6)
    pairs = {tuple(sorted(p)) for p in np.asarray(cube.springs).tolist()}
    assert pairs == set(itertools.combinations(range(8), 2))


@pytest.mark.parametrize("builder", BUILDERS)
def test_builders_stand_on_the_floor_centred(builder):
    lattice = builder()
    points = np.asarray(lattice.points)
    assert points[:, 2].min() == pytest.approx(0.0, abs=1e-7)
    np.testing.assert_allclose(np.asarray(lattice.com)[:2], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(lattice.frame), np.eye(3))


def test_pyramid_and_chair_shapes():
    pyramid = jm.lattices.pyramid(base=1.0, height=1.5)
    assert (pyramid.num_masses, pyramid.num_springs) == (5, 10)
    assert float(np.asarray(pyramid.points)[4, 2]) == pytest.approx(1.5)
    chair = jm.lattices.chair()
    assert (chair.num_masses, chair.num_springs) == (10, 31)
    # The backrest rises at the back (-x) of the chair.
    top = np.asarray(chair.points)[8:]
    assert np.all(top[:, 0] < 0) and np.all(top[:, 2] > 1.5)


@pytest.mark.parametrize("builder", BUILDERS)
def test_builders_are_rigid_frameworks(builder):
    """Every builder's springs hold its shape: the rigidity matrix has rank 3n - 6."""
    lattice = builder()
    p = np.asarray(lattice.points, dtype=float)
    n = p.shape[0]
    rows = []
    for i, j in np.asarray(lattice.springs):
        row = np.zeros(3 * n)
        d = p[j] - p[i]
        row[3 * j : 3 * j + 3] = d
        row[3 * i : 3 * i + 3] = -d
        rows.append(row)
    assert np.linalg.matrix_rank(np.array(rows), tol=1e-9) == 3 * n - 6


SQUARE = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]


@pytest.mark.parametrize(
    ("springs", "kwargs", "message"),
    [
        ([[0, 1], [1, 3]], {}, r"spring 1 = \(1, 3\) refers to mass 3, which does not exist"),
        ([[0, 1], [1, 0]], {}, r"spring 1 = \(1, 0\) duplicates spring 0 = \(0, 1\)"),
        ([[0, 1], [2, 2]], {}, r"spring 1 = \(2, 2\) connects mass 2 to itself"),
        (
            [[0, 1]],
            {"masses": [1.0, -2.0, 1.0]},
            r"mass 1 has mass -2; allowed: a finite number > 0",
        ),
        ([[0, 1]], {"masses": 0.0}, r"mass 0 has mass 0"),
        ([[0, 1]], {"stiffness": -1.0}, r"spring 0 = \(0, 1\) has stiffness -1"),
        ([[0, 1]], {"rest_lengths": [0.0]}, r"spring 0 = \(0, 1\) has rest length 0"),
        ([[0, 1]], {"frame": np.diag([1.0, 1.0, -1.0])}, r"right-handed"),
        ([[0, 1]], {"frame": np.ones((3, 3))}, r"orthonormal"),
    ],
)
def test_bad_lattices_raise_naming_the_culprit(springs, kwargs, message):
    with pytest.raises(ValueError, match=message):
        jm.lattices.from_points(SQUARE, springs, **kwargs)


def test_zero_length_spring_names_both_masses():
    with pytest.raises(ValueError, match=r"spring 0 = \(0, 1\) has zero length: masses 0 and 1"):
        jm.lattices.from_points([[0, 0, 0], [0, 0, 0], [1, 0, 0]], [[0, 1], [1, 2]])


def test_points_must_be_n_by_3():
    with pytest.raises(ValueError, match=r"shape \(num_masses, 3\)"):
        jm.lattices.from_points([[0, 0], [1, 1]], [[0, 1]])


def test_rest_length_matrix_is_identity_for_rest_shape_and_scales_prestress():
    lattice = jm.lattices.from_points(SQUARE, [[0, 1], [1, 2]], rest_lengths=[0.5, 2.0])
    table = np.asarray(lattice.rest_length_matrix(lattice.points))
    assert table[0, 1] == table[1, 0] == pytest.approx(0.5)
    assert table[1, 2] == pytest.approx(2.0)
    stretched = np.asarray(lattice.points) * np.array([2.0, 1.0, 1.0])
    table = np.asarray(lattice.rest_length_matrix(stretched))
    assert table[0, 1] == pytest.approx(1.0)  # the spring along x doubles


@settings(max_examples=25, deadline=None)
@given(
    st.integers(min_value=2, max_value=7).flatmap(
        lambda n: st.tuples(
            st.lists(st.tuples(*[st.floats(-2, 2, allow_nan=False)] * 3), min_size=n, max_size=n),
            st.lists(
                st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), min_size=1, max_size=12
            ),
        )
    )
)
def test_from_points_accepts_exactly_the_valid_lattices(data):
    points, springs = data
    points = np.array(points)
    keys = [tuple(sorted(s)) for s in springs]
    lengths = [np.linalg.norm(points[a] - points[b]) for a, b in springs]
    valid = (
        len(set(keys)) == len(keys)
        and all(a != b for a, b in springs)
        and all(d > 1e-9 * max(1.0, np.ptp(points)) for d in lengths)
    )
    if valid:
        lattice = jm.lattices.from_points(points, springs)
        assert lattice.num_springs == len(springs)
        np.testing.assert_allclose(np.asarray(lattice.rest_lengths), lengths, rtol=1e-5, atol=1e-6)
    else:
        with pytest.raises(ValueError, match="spring"):
            jm.lattices.from_points(points, springs)

"""The second paper's characters. The paper gives no drawings; each builder documents the
rods and joint ranges it chose from the paper's words (`notebooks/figures.ipynb` shows them).

Conventions: x forward, y left, z up; lengths in m, masses in kg, ranges in degrees in the
docstrings (radians in the `Joint`s). An angle about y is a right-handed turn about +y: a
positive angle turns a rod's +x end down (toward -z) and a hanging rod's lower end back
(toward -x). So for a figure facing +x a knee flexes (the foot goes back) with a positive
angle, a hip flexes (the thigh, and the foot, swing forward) with a negative one, and a
torso or head leans forward with a positive one. `tests/test_figure.py` checks each
builder's senses by moving its joints.
"""

import math
from collections.abc import Sequence

import numpy as np

from .figure import Figure, Joint

_Y = (0.0, 1.0, 0.0)
_X = (1.0, 0.0, 0.0)
_Z = (0.0, 0.0, 1.0)


def _deg(lo: float, hi: float) -> tuple[float, float]:
    return math.radians(lo), math.radians(hi)


def _polar(angle_deg: float, length: float) -> np.ndarray:
    """A vector in the x-z plane at `angle_deg` from +x, counter-clockwise toward +z."""
    a = math.radians(angle_deg)
    return np.array([math.cos(a), 0.0, math.sin(a)]) * length


def star_man(max_torque: float | Sequence[float] | None = None) -> Figure:
    """Mr. Star-Man (2D): five rods of 0.5 m radiating from one hub node, like a five-pointed
    star: the head (the root, straight up), two arms (18 degrees above horizontal, forward and
    backward) and two legs (54 degrees below horizontal). 5 rods, 6 nodes, 4 joint angles
    (each limb against the head), each with range -45..45 degrees about its rest direction.
    Masses: head 2 kg, arms 1 kg, legs 1.5 kg; rods 3 cm thick.

    He stands on his two feet (the leg tips, `feet`: front, then back), 0.59 m apart.

    `max_torque` (N m, one number or one per joint angle; default `None`, kinematic
    joints) limits the joints' strength (`Figure`).
    """
    hub = np.zeros(3)
    limbs = [90.0, 18.0, 162.0, -54.0, 234.0]  # head, front arm, back arm, front leg, back leg
    nodes = [hub] + [hub + _polar(a, 0.5) for a in limbs]
    rods = [(0, 1), (0, 2), (0, 3), (0, 4), (0, 5)]
    joints = [Joint(k, _Y, *_deg(-45, 45)) for k in range(1, 5)]
    return Figure(
        np.array(nodes),
        rods,
        masses=[2.0, 1.0, 1.0, 1.5, 1.5],
        joints=joints,
        radii=0.03,
        planar=True,
        name="star_man",
        max_torque=max_torque,
        feet=((4,), (5,)),
    )


def beryl_biped(max_torque: float | Sequence[float] | None = None) -> Figure:
    """Beryl Biped (2D): a torso with two two-part legs. The torso (the root, 0.6 m, 4 kg)
    stands up from the hip; each leg is a thigh (0.45 m, 1.5 kg) from the hip and a shin
    (0.45 m, 1 kg) from the knee, resting 10 degrees either side of vertical. 5 rods, 6
    nodes, 4 joint angles: hips -60..60 degrees against the torso (negative flexes: the
    thigh swings forward), knees 0..90 degrees (positive flexes: the shin, and the foot, go
    back, as a knee bends when the figure faces +x). Feet: the front leg's tip (as left),
    then the back leg's.

    `max_torque` (N m, one number or one per joint angle; default `None`, kinematic
    joints) limits the joints' strength (`Figure`).
    """
    hip = np.zeros(3)
    front = _polar(-80.0, 0.45)
    back = _polar(-100.0, 0.45)
    nodes = [hip, hip + _polar(90.0, 0.6), hip + front, hip + 2 * front, hip + back, hip + 2 * back]
    rods = [(0, 1), (0, 2), (2, 3), (0, 4), (4, 5)]
    # A knee bends backward: the shin's lower end turns toward -x, a positive angle about +y.
    joints = [
        Joint(1, _Y, *_deg(-60, 60)),
        Joint(2, _Y, *_deg(0, 90)),
        Joint(3, _Y, *_deg(-60, 60)),
        Joint(4, _Y, *_deg(0, 90)),
    ]
    return Figure(
        np.array(nodes),
        rods,
        masses=[4.0, 1.5, 1.0, 1.5, 1.0],
        joints=joints,
        radii=0.03,
        planar=True,
        name="beryl_biped",
        max_torque=max_torque,
        feet=((3,), (5,)),
    )


def _leg(nodes: list, at: int, vector) -> tuple[int, int]:
    nodes.append(nodes[at] + np.asarray(vector, dtype=float))
    return at, len(nodes) - 1


def cujo() -> Figure:
    """Cujo (3D, dog-like, 7 rods): a spine (the root, 0.8 m along x, 5 kg); four legs of
    0.43 m (0.6 kg; 0.4 m down and splayed 0.15 m sideways) hanging from its ends; a
    neck-and-head rod (0.35 m, 1 kg) rising forward at 45 degrees from the shoulders; a tail
    (0.3 m, 0.2 kg) rising backward at 45 degrees from the hips. Each rod's joint has two
    angles (the paper's Figure 6): a swing about the lateral axis y and a splay about the
    forward axis x (the head and tail: nod about y, turn about z). Ranges (degrees): legs
    swing -18..18 (negative: forward) and splay -7..7; head nod -15..15 and turn -10..10;
    tail -15..15 both ways.
    Average range 25.8 degrees.
    """
    nodes: list = [np.array([-0.4, 0.0, 0.4]), np.array([0.4, 0.0, 0.4])]  # hips, shoulders
    rods = [(0, 1)]
    half_width = 0.15
    for at, side in ((1, 1), (1, -1), (0, 1), (0, -1)):  # front left/right, back left/right
        rods.append(_leg(nodes, at, (0.0, side * half_width, -0.4)))
    rods.append(_leg(nodes, 1, _polar(45.0, 0.35)))
    rods.append(_leg(nodes, 0, _polar(135.0, 0.3)))
    joints = []
    for k in range(1, 5):
        joints += [Joint(k, _Y, *_deg(-18, 18)), Joint(k, _X, *_deg(-7, 7))]
    joints += [Joint(5, _Y, *_deg(-15, 15)), Joint(5, _Z, *_deg(-10, 10))]
    joints += [Joint(6, _Y, *_deg(-15, 15)), Joint(6, _Z, *_deg(-15, 15))]
    return Figure(
        np.array(nodes),
        rods,
        masses=[5.0, 0.6, 0.6, 0.6, 0.6, 1.0, 0.2],
        joints=joints,
        radii=0.04,
        name="cujo",
        feet=((2,), (3,), (4,), (5,)),
    )


def rex() -> Figure:
    """Rex (3D, 15 rods): a two-legged dinosaur. Pelvis (the root, 0.3 m across, 6 kg); chest
    (0.52 m forward and up, 5 kg), neck (0.3 m, 1 kg), head (0.35 m forward, 1.5 kg); a tail
    of three rods (0.43, 0.35, 0.32 m backward and down; 1.5, 0.8, 0.4 kg); per leg a thigh
    (0.5 m, 2 kg), shin (0.5 m, 1 kg) and foot (0.25 m forward, 0.4 kg); two small arms
    (0.27 m, 0.3 kg) from the chest.

    Two angles per joint, 28 in all (the paper's count, 2N - 2); about two thirds are fixed
    and 10 are free (the paper's 47 search variables with 4 rules), average range 42 degrees:
    each hip swings -30..30 about y (negative flexes: the leg swings forward) and splays
    -10..10 about x, each knee bends 0..40 about y (positive flexes: the foot goes back), each
    ankle turns -40..0 about y (negative lifts the toes: with the knee bent by an angle, the
    ankle at minus that angle sets the foot flat again); the tail's first rod turns -25..25
    about z and the neck nods -25..25 about y (positive: down). Every other angle is fixed
    at 0. Feet: each foot rod's two nodes (ankle, toe), left then right.
    """
    nodes: list = [np.array([0.0, 0.15, 1.0]), np.array([0.0, -0.15, 1.0])]  # hips L, R
    rods = [(0, 1)]
    # Every rod starts at a node an earlier rod reached: the chest and the tail start at the
    # hips and meet the body's midline at their other end.
    chest = _leg(nodes, 0, (0.45, -0.15, 0.2))
    neck = _leg(nodes, chest[1], (0.2, 0.0, 0.22))
    head = _leg(nodes, neck[1], (0.35, 0.0, 0.0))
    tail1 = _leg(nodes, 1, (-0.38, 0.15, -0.12))
    tail2 = _leg(nodes, tail1[1], (-0.33, 0.0, -0.12))
    tail3 = _leg(nodes, tail2[1], (-0.3, 0.0, -0.1))
    legs = []
    for hip in (0, 1):
        thigh = _leg(nodes, hip, (0.0, 0.0, -0.5))
        shin = _leg(nodes, thigh[1], (0.0, 0.0, -0.5))
        foot = _leg(nodes, shin[1], (0.25, 0.0, 0.0))
        legs.append((thigh, shin, foot))
    arms = [_leg(nodes, chest[1], (0.1, side * 0.12, -0.22)) for side in (1, -1)]
    rods += [chest, neck, head, tail1, tail2, tail3]
    for leg in legs:
        rods += list(leg)
    rods += arms
    index = {r: k for k, r in enumerate(rods)}
    fixed = lambda k, axis: Joint(k, axis, 0.0, 0.0)
    joints = []
    free = {
        (index[legs[0][0]], _Y): _deg(-30, 30),
        (index[legs[1][0]], _Y): _deg(-30, 30),
        (index[legs[0][0]], _X): _deg(-10, 10),
        (index[legs[1][0]], _X): _deg(-10, 10),
        (index[legs[0][1]], _Y): _deg(0, 40),
        (index[legs[1][1]], _Y): _deg(0, 40),
        (index[legs[0][2]], _Y): _deg(-40, 0),
        (index[legs[1][2]], _Y): _deg(-40, 0),
        (index[tail1], _Z): _deg(-25, 25),
        (index[neck], _Y): _deg(-25, 25),
    }
    for k in range(1, len(rods)):
        for axis in (_Y, _X if k in (index[legs[0][0]], index[legs[1][0]]) else _Z):
            joints.append(Joint(k, axis, *free[(k, axis)]) if (k, axis) in free else fixed(k, axis))
    masses = [6.0, 5.0, 1.0, 1.5, 1.5, 0.8, 0.4]
    masses += [2.0, 1.0, 0.4] * 2 + [0.3, 0.3]
    feet = tuple(tuple(foot) for _, _, foot in legs)
    return Figure(
        np.array(nodes), rods, masses=masses, joints=joints, radii=0.04, name="rex", feet=feet
    )


def bob() -> Figure:
    """Bob the Biped (3D, 9 rods, point feet): pelvis (the root, 0.3 m across, 6 kg), torso
    (from the left hip up to the shoulders on the midline, 0.57 m, 12 kg), head (0.3 m,
    4 kg), two thighs (0.45 m, 4 kg), two shins (0.45 m, 2.5 kg) ending in point feet, two
    arms (0.63 m, 2 kg) hanging from the shoulders.

    Two angles per joint, 16 in all; 6 fixed and 10 free with ranges a little under 25
    degrees on average (24.8): hips swing -15..15 about y (negative flexes: the leg swings
    forward) and splay -8..8 about x; knees bend 0..30 about y (positive flexes: the foot
    goes back); the torso leans -10..10 about y (positive: forward) and -8..8 about x; the
    arms swing -15..15 about y (positive: back). Fixed at 0: the knees' x angles, the head's
    two angles and the arms' x angles. Feet: the shins' lower ends, left then right.
    """
    nodes: list = [np.array([0.0, 0.15, 0.9]), np.array([0.0, -0.15, 0.9])]
    rods = [(0, 1)]
    torso = _leg(nodes, 0, (0.0, -0.15, 0.55))
    head = _leg(nodes, torso[1], (0.0, 0.0, 0.3))
    legs = []
    for hip in (0, 1):
        thigh = _leg(nodes, hip, (0.0, 0.0, -0.45))
        shin = _leg(nodes, thigh[1], (0.0, 0.0, -0.45))
        legs.append((thigh, shin))
    arms = [_leg(nodes, torso[1], (0.0, side * 0.2, -0.6)) for side in (1, -1)]
    rods += [torso, head] + [r for leg in legs for r in leg] + arms
    k_torso, k_head = 1, 2
    k_thighs = (3, 5)
    k_shins = (4, 6)
    k_arms = (7, 8)
    joints = [
        Joint(k_torso, _Y, *_deg(-10, 10)),
        Joint(k_torso, _X, *_deg(-8, 8)),
        Joint(k_head, _Y, 0.0, 0.0),
        Joint(k_head, _X, 0.0, 0.0),
    ]
    for t, sh in zip(k_thighs, k_shins, strict=True):
        joints += [Joint(t, _Y, *_deg(-15, 15)), Joint(t, _X, *_deg(-8, 8))]
        joints += [Joint(sh, _Y, *_deg(0, 30)), Joint(sh, _X, 0.0, 0.0)]
    for a in k_arms:
        joints += [Joint(a, _Y, *_deg(-15, 15)), Joint(a, _X, 0.0, 0.0)]
    masses = [6.0, 12.0, 4.0, 4.0, 2.5, 4.0, 2.5, 2.0, 2.0]
    feet = tuple((shin[1],) for _, shin in legs)
    return Figure(
        np.array(nodes), rods, masses=masses, joints=joints, radii=0.05, name="bob", feet=feet
    )


def snake(max_torque: float | Sequence[float] | None = None) -> Figure:
    """The snake of the third paper (its Figure 1; 2D): three rods of 0.3 m (1 kg each, 3 cm
    thick) in a line along x, lying on the floor. The middle rod is the root; the head (front,
    +x) and the tail (back) each turn against it about y, -90..90 degrees (a positive angle
    turns the head's tip down and the tail's tip up). 3 rods, 4 nodes, 2 joint angles.
    Body length 0.9 m.

    `max_torque` (N m, one number or one per joint angle; default `None`, kinematic
    joints) limits the joints' strength (`Figure`).
    """
    nodes = [np.array([x, 0.0, 0.0]) for x in (-0.15, 0.15, 0.45, -0.45)]
    rods = [(0, 1), (1, 2), (0, 3)]
    joints = [Joint(1, _Y, *_deg(-90, 90)), Joint(2, _Y, *_deg(-90, 90))]
    return Figure(
        np.array(nodes),
        rods,
        masses=[1.0, 1.0, 1.0],
        joints=joints,
        radii=0.03,
        planar=True,
        name="snake",
        max_torque=max_torque,
    )


def luxo(max_torque: float | Sequence[float] | None = None) -> Figure:
    """The Luxo lamp of the third paper (its Figure 2; 2D): a base (the root, 0.25 m along
    x on the floor, 1 kg), a lower arm (0.3 m, 0.3 kg) rising forward at 60 degrees from the
    base's back end, an upper arm (0.3 m, 0.3 kg) rising backward at 120 degrees from the
    lower arm's top, and a head (the lampshade, 0.2 m, 0.5 kg) pointing forward and down at
    -30 degrees from the upper arm's top. 4 rods, 5 nodes, 3 joint angles about y: the
    lower arm against the base -60..60 degrees (positive tips it forward), the upper arm
    against the lower -75..75, the head against the upper arm -60..60. Rods 3 cm thick.
    Body length 0.25 m (the base; the arms and head stay within it at rest).

    `max_torque` (N m, one number or one per joint angle; default `None`, kinematic
    joints) limits the joints' strength (`Figure`).
    """
    back = np.array([-0.1, 0.0, 0.0])
    elbow = back + _polar(60.0, 0.3)
    top = elbow + _polar(120.0, 0.3)
    nodes = [back, back + _polar(0.0, 0.25), elbow, top, top + _polar(-30.0, 0.2)]
    rods = [(0, 1), (0, 2), (2, 3), (3, 4)]
    joints = [
        Joint(1, _Y, *_deg(-60, 60)),
        Joint(2, _Y, *_deg(-75, 75)),
        Joint(3, _Y, *_deg(-60, 60)),
    ]
    return Figure(
        np.array(nodes),
        rods,
        masses=[1.0, 0.3, 0.3, 0.5],
        joints=joints,
        radii=0.03,
        planar=True,
        name="luxo",
        max_torque=max_torque,
    )

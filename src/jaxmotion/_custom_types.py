"""Type aliases shared by the public signatures (the way diffrax keeps `_custom_types.py`)."""

from typing import TypeAlias

from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | Float[ArrayLike, ""]
Key: TypeAlias = PRNGKeyArray

Points: TypeAlias = Float[Array, "num_points 3"]
Springs: TypeAlias = Int[Array, "num_springs 2"]
PerSpring: TypeAlias = Float[Array, " num_springs"]
PerMass: TypeAlias = Float[Array, " num_masses"]
Frame: TypeAlias = Float[Array, "3 3"]
Fitness: TypeAlias = Float[Array, " batch"]
Finite: TypeAlias = Bool[Array, " batch"]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Finite",
    "Fitness",
    "Float",
    "Frame",
    "Int",
    "Key",
    "PerMass",
    "PerSpring",
    "Points",
    "Scalar",
    "ScalarLike",
    "Springs",
]

"""What every search records: the fitness of every evaluation, in order."""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class History:
    """The fitness of every evaluation a search made, in the order it made them.

    - `fitness`: `(num_evaluations,)` float64; `-inf` marks a run that blew up.
    - `step`: `(num_evaluations,)` which step of the search made each evaluation (0 is the
        initial random population).

    Fitness is maximised.
    """

    fitness: np.ndarray
    step: np.ndarray

    def __post_init__(self):
        f = np.asarray(self.fitness, dtype=np.float64).reshape(-1)
        s = np.asarray(self.step, dtype=np.int64).reshape(-1)
        if f.shape != s.shape:
            raise ValueError(f"History needs one step per fitness; got {f.shape} and {s.shape}")
        object.__setattr__(self, "fitness", f)
        object.__setattr__(self, "step", s)

    def __len__(self) -> int:
        return self.fitness.shape[0]

    @property
    def best_so_far(self) -> np.ndarray:
        """Best fitness among the evaluations up to and including each one."""
        return np.maximum.accumulate(self.fitness) if len(self) else self.fitness

    @property
    def num_nonfinite(self) -> int:
        """How many evaluations blew up (fitness `-inf`)."""
        return int(np.sum(~np.isfinite(self.fitness)))

    @classmethod
    def concatenate(cls, parts: "list[History]") -> "History":
        if not parts:
            return cls(np.zeros(0), np.zeros(0, dtype=np.int64))
        return cls(
            np.concatenate([p.fitness for p in parts]), np.concatenate([p.step for p in parts])
        )

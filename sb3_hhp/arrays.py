"""Array helpers shared by the networks that score batches of observations (RND, the preference predictor)."""

import numpy as np


def distinct_rows(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``obs`` (compared byte for byte) in order of first appearance, and the index of each row
    among them: ``distinct[inverse]`` is ``obs``."""
    first: dict[bytes, int] = {}
    inverse = np.fromiter((first.setdefault(row.tobytes(), len(first)) for row in obs.reshape(len(obs), -1)),
                          dtype=np.int64, count=len(obs))
    keep = np.zeros(len(first), dtype=np.int64)
    keep[inverse[::-1]] = np.arange(len(obs) - 1, -1, -1)  # the first row of each: written last
    return obs[keep], inverse

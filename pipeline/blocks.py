"""Cache-sized pieces of a large array, for passes that would otherwise build full-size
temporaries (masks, float64 copies) of a 24 Mpixel map."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np


def flat_blocks(arr: np.ndarray, size: int) -> Iterator[np.ndarray]:
    """``arr`` flattened, in consecutive pieces of at most ``size`` elements (views where
    ``arr`` is contiguous).

    Parameters
    ----------
    arr : numpy.ndarray
        Any array.
    size : int
        Elements per piece (> 0).

    Returns
    -------
    iterator of numpy.ndarray
        1-D pieces, in order.
    """
    flat = np.asarray(arr).reshape(-1)
    for i in range(0, flat.size, size):
        yield flat[i : i + size]

"""An even subsample of a recording's returns, chosen by a hash of each return's (scan, beam) pair: the same
returns on every run and every machine, and a draw of its own for every seed (the targetless fit's sample and its
segmentation sample, the DH search's starts, the marker surfaces' returns).

Array shapes: K pairs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from lrfcal.types import IntArray

#: an odd 64-bit constant (2^64 / golden ratio) that scrambles a salted key (:func:`hash_key`)
_SCRAMBLE = 0x9E3779B97F4A7C15


def hash_key(scan: IntArray, beam: IntArray, seed: int = 0) -> NDArray[np.uint64]:
    """The hash of every (scan, beam) pair (K,) that :func:`hash_sample` ranks them by, in [0, 2^31).

    Seed 0 is the plain hash of the pair. Another seed scrambles it: an exclusive or with the seed's own multiple of
    :data:`_SCRAMBLE`, a multiplication by it and an exclusive or with the key's high bits, a bijection of the 64-bit
    key whose low 31 bits rank the pairs anew for every seed (two seeds' subsamples of a fraction f of the pairs share
    about f of them). Adding the seed to the plain hash, as this did before, only turned the ranking cyclically:
    every seed then chose nearly the same subsample."""
    key = np.asarray(scan, dtype=np.uint64) * np.uint64(2654435761)
    key += np.asarray(beam, dtype=np.uint64) * np.uint64(40503)
    if seed:
        key ^= np.uint64((seed * _SCRAMBLE) & 0xFFFF_FFFF_FFFF_FFFF)
        key *= np.uint64(_SCRAMBLE)
        key ^= key >> np.uint64(31)
    key &= np.uint64((1 << 31) - 1)  # the remainder modulo 2^31 of an unsigned integer, without a division
    return key


def hash_sample(scan: IntArray, beam: IntArray, n: int, seed: int = 0) -> IntArray:
    """Indices of an even subsample of at most n of the (scan, beam) pairs (K,), chosen by a hash of the pair
    (salted by seed), in their original order."""
    K = len(scan)
    if n >= K:
        return np.arange(K)
    return np.sort(np.argsort(hash_key(scan, beam, seed), kind="stable")[:n])


__all__ = ["hash_key", "hash_sample"]

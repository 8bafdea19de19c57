"""Random generators derived from one root seed.

Every stage, scene, drop and frame gets its own generator from ``numpy.random.SeedSequence``. A child is
identified by its *name* (stage name and item key), not by the order in which it was requested, so the
stream an item sees is the same whatever the number of workers, the order items run in, or whether the
run was interrupted and resumed. This is what ``SeedSequence.spawn`` does with a counter, made
independent of call order: the child's ``spawn_key`` is derived from the name.

Examples
--------
>>> a = item_rng(0, "simulate", "kitchen/drop0001").random()
>>> b = item_rng(0, "simulate", "kitchen/drop0001").random()
>>> a == b
True
"""

from __future__ import annotations

import hashlib

import numpy as np


def _name_words(name: str) -> tuple[int, ...]:
    """Four 32-bit words from a SHA-256 of ``name`` (stable across Python runs, unlike ``hash``)."""
    digest = hashlib.sha256(name.encode("utf-8")).digest()
    return tuple(int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4))


def item_seed(root_seed: int, *names: str) -> np.random.SeedSequence:
    """SeedSequence of the item named by ``names`` (e.g. ``("simulate", "kitchen/drop0001")``)."""
    if root_seed < 0:
        raise ValueError(f"seed must be >= 0, got {root_seed}")
    key: tuple[int, ...] = ()
    for n in names:
        key += _name_words(n)
    return np.random.SeedSequence(entropy=root_seed, spawn_key=key)


def item_rng(root_seed: int, *names: str) -> np.random.Generator:
    """Generator for the item named by ``names``; see :func:`item_seed`."""
    return np.random.default_rng(item_seed(root_seed, *names))

"""Every PRNG stream of a population run, derived in one place from (population seed, purpose, index).

The root is ``PRNGKey(population.seed)``. Each purpose owns a disjoint range of ``fold_in`` data
(offsets far above any seed index), so adding a purpose or a seed never shifts another stream and
seed ``i``'s numbers do not depend on how many seeds train beside it:

    seed           fold_in(root, i)                                     seed i's training
    sa_restart     fold_in(fold_in(root, i), SA + k)                   seed i's episode restart, SA iteration k
    sa             fold_in(root, SA + k)                                SA collection of iteration k
    xp             fold_in(root, XP)                                    final cross-play
    gif            fold_in(fold_in(root, GIF), i)                       seed i's self-play GIF
    train_archive  fold_in(fold_in(root, TRAIN_ARCHIVE + u), i)         seed i's archived episode at update u

Results and stored checkpoints depend on these exact derivations: change none of them.
"""

from __future__ import annotations

import jax

OFFSETS = {"seed": 0, "sa": 1 << 20, "xp": 1 << 21, "gif": 1 << 22, "train_archive": 1 << 23}
PURPOSES = (*OFFSETS, "sa_restart")


def derive_key(seed: int, purpose: str, index: int = 0, member: int | None = None) -> jax.Array:
    """The key of stream ``purpose`` (see the module table): ``index`` within the purpose (update,
    iteration, seed for ``seed``), ``member`` the seed it is for when the purpose has one per seed."""
    if purpose not in PURPOSES:
        raise ValueError(f"unknown key purpose {purpose!r}; one of {', '.join(PURPOSES)}")
    root = jax.random.PRNGKey(seed)
    if purpose == "sa_restart":  # a branch of the seed's own stream: restarts follow the seed, not the shard
        return jax.random.fold_in(jax.random.fold_in(root, member), OFFSETS["sa"] + index)
    key = jax.random.fold_in(root, OFFSETS[purpose] + index)
    return key if member is None else jax.random.fold_in(key, member)

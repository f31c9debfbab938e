"""Hand-counted spikes of a tiny PopSAN, shared by the operation-count and energy tests."""

import jax.numpy as jnp


def tiny_spikes():
    """Tiny PopSAN: obs 2 x enc pop 2 = 4 encoder neurons, hidden (3, 2), 1 action x pop 2.

    T = 2 timesteps, B = 2 observations. Spike counts by hand:
      encoder: obs0 t0 2, t1 1; obs1 t0 0, t1 4          -> 7
      hidden1: obs0 t0 1, t1 2; obs1 t0 3, t1 0          -> 6
      hidden2: obs0 t0 0, t1 1; obs1 t0 2, t1 1          -> 4
      output:  obs0 t0 1, t1 1; obs1 t0 0, t1 2          -> 4
    """
    enc = [[[1, 1, 0, 0], [0, 0, 0, 0]], [[0, 1, 0, 0], [1, 1, 1, 1]]]
    h1 = [[[1, 0, 0], [1, 1, 1]], [[0, 1, 1], [0, 0, 0]]]
    h2 = [[[0, 0], [1, 1]], [[0, 1], [1, 0]]]
    out = [[[1, 0], [0, 0]], [[0, 1], [1, 1]]]
    return tuple(jnp.asarray(s, jnp.float32) for s in (enc, h1, h2, out))


SIZES = (4, 3, 2, 2)


SIZES = (4, 3, 2, 2)

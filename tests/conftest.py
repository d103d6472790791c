"""Shared fixtures: a fixed PRNG key, and a guard on the floating-point precision.

* ``key``: ``jax.random.key(0)``, for tests that need a key and no particular one.
* Every test must run, and leave JAX, in its default precision: float32
  (``jax_enable_x64`` off) with standard dtype promotion. jaxcos's estimator
  and its tolerances are float32 (docs/model.md section 7); a test that turned
  on x64 would check other numbers than those the library computes, and would
  change them for the tests after it.
"""

import jax
import jax.numpy as jnp
import pytest


@pytest.fixture
def key():
    """A fixed PRNG key, ``jax.random.key(0)``."""
    return jax.random.key(0)


def _precision():
    return dict(x64=bool(jax.config.jax_enable_x64), promotion=jax.config.jax_numpy_dtype_promotion,
                float=str(jnp.result_type(float)))


DEFAULT_PRECISION = dict(x64=False, promotion="standard", float="float32")


@pytest.fixture(autouse=True)
def float32_guard():
    """Fail a test that starts, or leaves JAX, outside float32 with standard promotion."""
    assert _precision() == DEFAULT_PRECISION, f"JAX is not in its default precision before the test: {_precision()}"
    yield
    assert _precision() == DEFAULT_PRECISION, f"the test left JAX outside its default precision: {_precision()}"

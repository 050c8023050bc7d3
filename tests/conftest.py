"""Shared test set-up: strict numpy rank promotion, keys, tiny configs."""

import jax
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture
def key():
    return jax.random.key(0)

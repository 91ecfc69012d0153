"""linalg.check_key: the one PRNG-key check of features.lines (any 1-D uint32 key data) and
tuning.optimize.fit (raw_shape=(2,): PRNGKey's pair), which each had a copy."""

import jax
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.linalg import check_key


def test_check_key_takes_typed_and_raw_keys():
    for key in (jax.random.key(0), jax.random.PRNGKey(0), np.zeros(2, np.uint32)):
        check_key(key)
        check_key(key, raw_shape=(2,))
    check_key(np.zeros(4, np.uint32))  # any 1-D key data without raw_shape (features.lines)


@pytest.mark.parametrize("key, raw_shape", [
    (0, None), (np.uint32(1), None), (np.zeros(2, np.int32), None), (np.zeros((1, 2), np.uint32), None),
    (jax.random.split(jax.random.key(0)), None), (np.zeros(4, np.uint32), (2,)),
])
def test_check_key_names_the_argument(key, raw_shape):
    with pytest.raises(InputError, match=r"^rng: expected a PRNG key \(jax\.random\.PRNGKey\(seed\) or "
                                         r"jax\.random\.key\(seed\)\), got "):
        check_key(key, "rng", raw_shape=raw_shape)

"""The env contract under bad input: clear errors naming the problem, nothing silently ignored, and
long-lived objects (the CPU vector env) still usable after a rejected call. Short, seeded runs only."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.vector import make_vec_env

ENV = "TableClearing-IRB120-v1"


# --------------------------------------------------------------------------- CPU vector env
@pytest.fixture(scope="module")
def venv():
    env = make_vec_env(ENV, 2, backend="cpu", obs_mode="state", max_episode_steps=50)
    yield env
    env.close()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_vector_env_rejects_non_finite_action_and_stays_usable(venv, bad):
    venv.reset(seed=0)
    actions = torch.zeros(2, 5)
    actions[1, 2] = bad
    with pytest.raises(ValueError, match=r"NaN or inf for env index \[1\]"):
        venv.step(actions)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))  # the workers are alive
    assert obs.shape[0] == 2 and torch.isfinite(rew).all()


@pytest.mark.parametrize(
    "bad,err,match",
    [
        ("left", TypeError, "str"),
        ([["a"] * 5] * 2, TypeError, "dtype"),
        (np.zeros((2, 5), dtype=object), TypeError, "dtype object"),
        (np.zeros((2, 5), dtype=bool), TypeError, "dtype bool"),
        (torch.zeros(2, 5, dtype=torch.complex64), TypeError, "complex"),
        ({"action": 0}, TypeError, "dict"),
        ([[0.0] * 5, [0.0] * 4], ValueError, "rectangular"),
        (np.zeros((2, 4)), ValueError, "shape"),
    ],
)
def test_vector_env_rejects_wrong_types_and_stays_usable(venv, bad, err, match):
    venv.reset(seed=0)
    with pytest.raises(err, match=match):
        venv.step(bad)
    venv.step(np.zeros((2, 5), dtype=np.int64))  # integers are numbers; the workers are alive

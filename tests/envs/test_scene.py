"""The shared scene (``envs/scene.py``): the batched contact-pair layout of :class:`Contacts`."""

from __future__ import annotations

import gymnasium as gym

import maniskill_irb120  # noqa: F401  (registers the env)

ENV = "TableClearing-IRB120-v1"


def test_contact_pairs_one_fixed_layout():
    env = gym.make(ENV, obs_mode="state")
    env.reset(seed=0)
    u = env.unwrapped
    pairs = u.contacts.pairs
    links = {a.name for a, b in pairs if b in u.scene_actors and a is not u.obj}
    assert "base_link" not in links and "tcp" not in links  # stands on the table / has no shape
    assert len(pairs) == len(links) * 4 + 4 + 2
    assert u.contacts.impulses().shape == (len(pairs), 1, 3)
    env.close()

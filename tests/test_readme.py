"""The README's quick start runs as printed: a random-action episode, shielded, for its full
length with the RL defaults."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _block_after(heading: str) -> str:
    text = README.read_text()
    section = text[text.index(heading) :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_quick_start_flies_a_random_episode_to_its_end_with_the_shield():
    scope: dict = {}
    exec(compile(_block_after("## The environment"), "README.md", "exec"), scope)
    env, term, trunc = scope["env"], scope["term"], scope["trunc"]
    raw = env.unwrapped
    assert raw.num_cycles == raw.max_cycles == 4800
    assert set(trunc) == set(raw.possible_agents) and all(trunc.values())  # every UAV to the end
    assert not any(term.values())
    assert raw.config.reward.shape == "exp" and raw.config.terminate_on_collision == "agent"
    env.close()

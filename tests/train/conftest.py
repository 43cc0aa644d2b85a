"""A finished tiny Dyna-Q run, shared by the tests of the scripts that start from one."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.train import load_script


@pytest.fixture(scope="session")
def tabular_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished (tiny) Dyna-Q run with both belief models; the tests only read its folder.

    Its physics model is fitted on 8 greedy episodes, and it has no final evaluation: the
    tests read its agent and its models, never its results.
    """
    tabular = load_script("dyna_q_peg")
    args = tabular.Args(
        out_dir=str(tmp_path_factory.mktemp("tabular")),
        num_envs=4,
        rounds=2,
        max_steps=15,
        eval_every=2,
        eval_episodes=2,
        final_episodes=0,
        particles=24,
        mode_episodes=8,
    )
    return Path(tabular.run(args)["run_dir"])

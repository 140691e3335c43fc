"""Bring your own controller: `diacc eval --policy package.module:factory`."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from diacc.cli import main
from diacc.envs.actions import ACCELERATE
from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import EPISODES_FILE, read_csv
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy, parse_policy

EXAMPLE = "examples.keep_right_controller:make"
CELL = Cell("train-50", 12, 0.5, "D1")


def test_example_controller_drives_the_cavs_on_pettingzoo_observations():
    policy = build_policy(parse_policy(EXAMPLE))
    driver = EpisodeDriver(policy, policy.env_config(CELL, EvalSettings(episode_steps=5)))
    try:
        driver.reset(CELL.seed(0, "test"))
        obs = driver._obs
        actions = policy.act(obs, first_step=True)
        assert actions.shape == (6,) and np.all(actions[obs.alive] == ACCELERATE)
        assert driver.cfg.psar_enabled  # the controller's requests go through PSAR
    finally:
        driver.close()


def test_eval_runs_a_controller_deterministically_in_workers_too(tmp_path):
    argv = ["eval", "--policy", EXAMPLE, "--grid", "train", "--episodes", "2"]
    argv += ["--episode-steps", "20", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    assert main([*argv, "--out", str(tmp_path / "b"), "--workers", "2"]) == 0
    rows = read_csv(tmp_path / "a" / EPISODES_FILE)
    assert {r["policy"] for r in rows} == {EXAMPLE} and {r["psar"] for r in rows} == {"True"}
    assert (tmp_path / "a" / EPISODES_FILE).read_bytes() == (
        tmp_path / "b" / EPISODES_FILE
    ).read_bytes()


@pytest.fixture()
def user_module(tmp_path, monkeypatch):
    """A module ``my_controllers`` of good and bad factories, importable in this test."""
    (tmp_path / "my_controllers.py").write_text(
        textwrap.dedent(
            """
            def plain():  # a bare callable on the observation dict
                return lambda observations: {agent: 4 for agent in observations}

            def broken():
                raise RuntimeError("no licence key")

            def number():
                return 3

            def bad_action():
                return lambda observations: {agent: 9 for agent in observations}

            def not_a_dict():
                return lambda observations: [0] * len(observations)

            class Divides:  # a user's bug at the third step
                steps = 0

                def act(self, observations):
                    self.steps += 1
                    return {agent: 1 // (3 - self.steps) for agent in observations}

            class ForgetsToReset:
                def reset(self, seed):
                    raise KeyError("no state yet")

                def act(self, observations):
                    return {}

            def divides():
                return Divides()

            def bad_reset():
                return ForgetsToReset()

            def hangs():
                def act(observations):
                    while True:
                        try:
                            pass
                        except Exception:  # swallows what it can: must not swallow the limit
                            pass
                return act

            def truthy():
                return lambda observations: {agent: True for agent in observations}
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return "my_controllers"


def test_a_plain_callable_is_a_controller(user_module):
    policy = build_policy(PolicySpec(f"{user_module}:plain"))
    driver = EpisodeDriver(policy, policy.env_config(CELL, EvalSettings(episode_steps=3)))
    try:
        driver.reset(CELL.seed(0, "test"))
        assert np.all(policy.act(driver._obs, True)[driver._obs.alive] == 4)
        driver.step()
    finally:
        driver.close()


@pytest.mark.parametrize(
    "spec, message",
    [
        ("no_such_module:make", "cannot import module 'no_such_module' (ModuleNotFoundError"),
        ("my_controllers:missing", "module 'my_controllers' has no callable 'missing'"),
        ("my_controllers:broken", "broken() raised RuntimeError: no licence key"),
        ("my_controllers:number", "returned int, which is neither callable nor has an act"),
        ("my_controllers:bad_action", "the action of cav_0 is 9; actions are 0..4"),
        ("my_controllers:truthy", "at step 0 in cell train-25_N25_rho0.40_D1: the action of cav_0"),
        ("my_controllers:not_a_dict", "returned list; a controller returns a dict"),
        ("my_controllers:plain", "--actions sampled applies to checkpoints"),
    ],
)
def test_bad_controllers_are_one_line_errors(user_module, tmp_path, capsys, spec, message):
    argv = ["eval", "--policy", spec, "--grid", "train", "--episodes", "1"]
    argv += ["--episode-steps", "3", "--no-progress", "--out", str(tmp_path / "out")]
    if spec.endswith(":plain"):
        argv += ["--actions", "sampled"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("diacc: error:") and err.count("\n") == 1


def test_the_example_runs_to_the_end_of_the_road(tmp_path):
    """CAVs leave the road within 330 steps: the controller must stop seeing them (issue 61)."""
    grid = tmp_path / "cell.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\nn_vehicles = 12\ncav_penetration = 0.5\nstyle_mix = "D1"\n'
    )
    argv = ["eval", "--policy", EXAMPLE, "--grid", str(grid), "--episodes", "1"]
    assert main([*argv, "--episode-steps", "330", "--no-progress", "--out", str(tmp_path)]) == 0
    rows = read_csv(tmp_path / EPISODES_FILE)
    assert float(rows[0]["arrived_fraction"]) > 0  # some CAVs did leave the road


class _Spy:
    """Records how many agents it was shown at each step."""

    def __init__(self) -> None:
        self.shown: list[int] = []

    def act(self, observations):
        self.shown.append(len(observations))
        return {agent: ACCELERATE for agent in observations}


def test_a_controller_sees_every_cav_of_a_demand_cell():
    """With a slot per CAV, every CAV on the road is handed to the controller, every step."""
    cell = Cell("train-50", 0, 0.5, "D1", inflow_vph=1800, demand_s=30)
    policy = build_policy(PolicySpec(EXAMPLE))
    spy = _Spy()
    policy.controller._act = spy.act  # a controller that counts what it is shown
    settings = EvalSettings(episode_steps=40, agent_slots="every")
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    on_road = []
    try:
        driver.reset(cell.seed(0, "test"))
        while not driver.done:
            on_road.append(int(driver._obs.alive.sum()))
            driver.step()
    finally:
        driver.close()
    assert spy.shown == on_road and max(on_road) > 1


@pytest.mark.parametrize(
    "spec, message",
    [
        (
            "my_controllers:divides",
            "act() raised ZeroDivisionError: integer division or modulo by zero at step 2 "
            "in cell train-25_N25_rho0.40_D1",
        ),
        ("my_controllers:bad_reset", "reset(seed) raised KeyError: 'no state yet' before the"),
        ("my_controllers:hangs", "act() did not return within 0.5 s at step 0 in cell train-25"),
    ],
)
def test_a_fault_inside_a_controller_is_its_traceback_and_one_line(
    user_module, tmp_path, capsys, spec, message
):
    """The user's frames, then one line of ours naming controller, cell and step (issue 61)."""
    argv = ["eval", "--policy", spec, "--grid", "train", "--episodes", "1", "--no-progress"]
    argv += ["--episode-steps", "4", "--controller-timeout", "0.5", "--out", str(tmp_path)]
    assert main(argv) == 2
    *trace, line = capsys.readouterr().err.splitlines()
    assert line.startswith(f"diacc: error: controller {spec}: ") and message in line
    if not spec.endswith("hangs"):  # their own frame, not ours
        assert 'my_controllers.py", line' in trace[1] and "diacc" not in "\n".join(trace)


def test_a_controller_answers_by_the_rules_of_env_step():
    """A 0-d integer array is an action there, so it is one here too."""
    policy = build_policy(PolicySpec(EXAMPLE))
    policy.controller._act = lambda observations: {a: np.array(ACCELERATE) for a in observations}
    driver = EpisodeDriver(policy, policy.env_config(CELL, EvalSettings(episode_steps=2)))
    try:
        driver.reset(CELL.seed(0, "test"))
        assert np.all(policy.act(driver._obs, True)[driver._obs.alive] == ACCELERATE)
    finally:
        driver.close()

"""Replay one scorecard episode to its first collision and print both vehicles before it.

    python benchmarks/studies/suite-training/replay_crash.py POLICY SUITE EPISODE_SEED [BACKEND]

POLICY as ``diacc scorecard --policy`` takes it (``heuristic``, a checkpoint ...), SUITE a
scorecard suite (its first cell is played), EPISODE_SEED the ``seed`` column of the
card's ``episodes.csv``, on the `test` stream with the scorecard's settings. Prints, for
the last five decision steps, both vehicles' kind, driver style, lane, position, lateral
offset, speed and the PSAR rule that changed the CAV's action (0: none).
"""

from __future__ import annotations

import sys
from collections import deque

from diacc.envs.episode import EpisodeDriver
from diacc.experiments.policies import PolicySpec, build_policy
from diacc.experiments.scorecard import SUITES, ScorecardConfig, _settings, suite_cells

FIELDS = ("x_m", "y_m", "speed_mps", "lane", "is_cav", "style")


def main() -> None:
    if len(sys.argv) < 4 or sys.argv[2] not in SUITES or not sys.argv[3].isdigit():
        suites = ", ".join(SUITES)
        sys.exit(f"usage: replay_crash.py POLICY SUITE EPISODE_SEED [BACKEND]; SUITE: {suites}")
    name, suite, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
    backend = sys.argv[4] if len(sys.argv) > 4 else "highway"
    spec = PolicySpec(name)
    settings = _settings(ScorecardConfig(spec, "unused"), suite, backend)
    cell = suite_cells(SUITES[suite], "test")[0]
    policy = build_policy(spec)
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    history: deque = deque(maxlen=5)  # (step, {field: (V,)}, (V,) PSAR rule)
    try:
        driver.reset(seed)
        while not driver.done:
            state = driver.step()
            fields = {f: getattr(state, f)[0].copy() for f in FIELDS}
            history.append((driver.steps, fields, driver.psar_rule.copy()))
            if len(state.collisions):
                _, i, j = state.collisions[0]
                print(f"collision at step {driver.steps}: vehicles {i} and {j}")
                for step, f, rule in history:
                    for v in (i, j):
                        kind = "CAV" if f["is_cav"][v] else f"HDV style {f['style'][v]}"
                        print(
                            f"step {step} {kind} {v}: lane {f['lane'][v]} x {f['x_m'][v]:.1f} m "
                            f"y {f['y_m'][v]:.2f} m {f['speed_mps'][v]:.1f} m/s PSAR rule {rule[v]}"
                        )
                return
        print(f"no collision in {driver.steps} steps")
    finally:
        driver.close()


if __name__ == "__main__":
    main()

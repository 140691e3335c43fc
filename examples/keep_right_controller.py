"""A controller of your own for `diacc eval --policy examples.keep_right_controller:make`.

It acts on the PettingZoo observations of `diacc.parallel_env` (the "dict" format):
each CAV accelerates, and once its lane ends within 100 m it asks for the lane on its
right (in the agents' frame lanes always drop on the left). PSAR checks every request.
"""

REMAIN, LEFT, RIGHT, ACCELERATE, DECELERATE = range(5)


class KeepRight:
    def reset(self, seed: int) -> None:
        """Called before every episode with its seed (nothing to remember here)."""

    def act(self, observations: dict) -> dict:
        actions = {}
        for agent, obs in observations.items():
            lane_ends_soon = obs["self_state"][5] < 1.0  # lane end / 100 m, 1: not within 100 m
            right_exists = bool(obs["lane_mask"][2])  # ego, left, right
            actions[agent] = RIGHT if lane_ends_soon and right_exists else ACCELERATE
        return actions


def make() -> KeepRight:
    return KeepRight()

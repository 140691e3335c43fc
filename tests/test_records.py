"""Batched records (issue 59): concat, env selection, row masks and the unbatched
view, derived once from the axes each field declares."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from diacc.records import Batched, env_events, per_env, per_env_items, per_env_record, shared


@dataclass
class Step(Batched):
    reward: np.ndarray = per_env("E")
    speed: np.ndarray = per_env("E, C")
    hits: np.ndarray = env_events("env, i, j")


def batch(n_envs: int, first: int = 0) -> Step:
    envs = np.arange(first, first + n_envs)
    return Step(
        reward=envs.astype(float),
        speed=np.repeat(envs[:, None], 2, axis=1).astype(float),
        hits=np.array([[e - first, e, e + 1] for e in envs], np.int32),
    )


def test_concat_renumbers_events_and_selection_keeps_the_batch_axis():
    joined = Step.concat([batch(2), batch(3, first=2)])
    assert joined.n_rows == 5 and joined.hits[:, 0].tolist() == [0, 1, 2, 3, 4]
    picked = joined.rows(np.array([3, 1]))
    assert picked.reward.tolist() == [3.0, 1.0] and picked.speed.shape == (2, 2)
    assert picked.hits.tolist() == [[0, 3, 4], [1, 1, 2]]  # renumbered, env-major
    one = joined.env(4)
    assert one.speed.shape == (1, 2) and one.hits.tolist() == [[0, 4, 5]]
    assert joined.rows(joined.reward > 2.5).reward.tolist() == [3.0, 4.0]


def test_where_rows_zeroes_envs_not_kept_and_unbatched_drops_the_env_axis():
    kept = batch(3).where_rows(np.array([True, False, True]))
    assert kept.reward.tolist() == [0.0, 0.0, 2.0] and kept.speed[1].tolist() == [0.0, 0.0]
    assert kept.hits[:, 0].tolist() == [0, 2]
    view = batch(3).unbatched(1)
    assert view.reward == 1.0 and isinstance(view.reward, float)
    assert view.speed.shape == (2,) and view.hits.tolist() == [[1, 2]]


def test_a_field_without_axes_is_an_error_naming_it():
    @dataclass
    class Bare(Batched):
        x: np.ndarray

    with pytest.raises(TypeError, match=r"Bare\.x declares no axes"):
        Bare(np.zeros(1)).env(0)


@dataclass
class Outer(Batched):
    step: Step = per_env_record()
    kept: Step = per_env_record(keeps_batch=True)
    extra: Step | None = per_env_record()
    notes: list = per_env_items()


def outer(n_envs: int, first: int = 0) -> Outer:
    notes = [None if e % 2 else f"env {e}" for e in range(first, first + n_envs)]
    return Outer(batch(n_envs, first), batch(n_envs, first), None, notes)


def test_records_and_lists_are_cut_by_env_like_arrays():
    joined = Outer.concat([outer(2), outer(3, first=2)])
    assert joined.n_rows == 5 and joined.step.hits[:, 0].tolist() == [0, 1, 2, 3, 4]
    assert joined.extra is None and joined.notes == ["env 0", None, "env 2", None, "env 4"]
    picked = joined.rows(np.array([4, 2]))
    assert picked.step.reward.tolist() == [4.0, 2.0] and picked.notes == ["env 4", "env 2"]
    assert picked.kept.hits.tolist() == [[0, 4, 5], [1, 2, 3]]
    masked = joined.where_rows(np.array([True, True, False, True, True]))
    assert masked.step.reward.tolist() == [0.0, 1.0, 0.0, 3.0, 4.0] and masked.notes[2] is None
    view = joined.unbatched(2)
    assert view.step.reward == 2.0 and view.step.speed.shape == (2,) and view.notes == "env 2"
    assert view.kept.speed.shape == (1, 2) and view.kept.hits.tolist() == [[0, 2, 3]]


def test_concat_refuses_a_record_field_none_in_some_records_only():
    with_extra = Outer(batch(1), batch(1), batch(1), [None])
    with pytest.raises(ValueError, match=r"Outer.concat: extra is None in some"):
        Outer.concat([outer(1), with_extra])


def test_set_rows_writes_envs_in_place_and_replaces_their_events():
    target, part = outer(4), outer(2, first=10)
    target.set_rows(np.array([3, 1]), part)
    assert target.step.reward.tolist() == [0.0, 11.0, 2.0, 10.0]
    assert target.step.hits.tolist() == [[0, 0, 1], [1, 11, 12], [2, 2, 3], [3, 10, 11]]
    assert target.notes == ["env 0", None, "env 2", "env 10"] and target.extra is None


def test_a_shared_field_is_kept_by_every_row_operation():
    @dataclass
    class Model(Batched):
        gain: np.ndarray = per_env("E, V")
        exponent: float = shared()

    model = Model(np.arange(6.0).reshape(3, 2), 4.0)
    assert model.n_rows == 3 and Model.concat([model, model]).exponent == 4.0
    assert model.env(2).exponent == 4.0 and model.where_rows(np.ones(3, bool)).exponent == 4.0
    model.set_rows(np.array([0]), Model(np.full((1, 2), 9.0), 1.0))
    assert model.gain[0].tolist() == [9.0, 9.0] and model.exponent == 4.0


def test_copy_shares_no_array_and_keeps_what_is_not_one():
    original = outer(3)
    copied = original.copy()
    copied.step.speed[0] = -1.0
    copied.kept.hits[0, 1] = -1
    copied.notes[0] = "changed"
    assert original.step.speed[0].tolist() == [0.0, 0.0] and original.kept.hits[0, 1] == 0
    assert original.notes[0] == "env 0" and copied.extra is None
    assert copied.step.reward.tolist() == original.step.reward.tolist()


def test_stack_adds_a_leading_axis_and_arrays_name_the_per_env_ones():
    @dataclass
    class Obs(Batched):
        speed: np.ndarray = per_env("E, C")
        alive: np.ndarray = per_env("E")

    steps = [Obs(np.full((2, 3), float(t)), np.ones(2, bool)) for t in range(4)]
    stacked = Obs.stack(steps)
    assert stacked.speed.shape == (4, 2, 3) and stacked.speed[:, 0, 0].tolist() == [0, 1, 2, 3]
    assert list(stacked.arrays()) == ["speed", "alive"] and stacked.arrays()["alive"].shape == (
        4,
        2,
    )
    assert list(batch(2).arrays()) == ["reward", "speed"]  # event rows are not per-env arrays
    with pytest.raises(TypeError, match=r"Step\.stack: only a record of per-env arrays"):
        Step.stack([batch(2), batch(2)])

"""Ray scale-out on a real local Ray instance limited to 2 CPUs: same files as the local path."""

from __future__ import annotations

import json

import pytest
import torch

ray = pytest.importorskip(
    "ray", reason='Ray is not installed (optional extra: pip install -e ".[ray]")'
)

from diacc.cli import main  # noqa: E402
from diacc.config import TrainConfig, override  # noqa: E402
from diacc.experiments.evaluate import evaluate  # noqa: E402
from diacc.experiments.grid import make_cell  # noqa: E402
from diacc.experiments.policies import EvalSettings, parse_policy  # noqa: E402
from diacc.experiments.scaleout import RayEngine, run_sweep, sweep_configs  # noqa: E402
from diacc.learn.progress import TIMING_KEYS  # noqa: E402

#: progress.jsonl keys that measure time, not learning


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def _cells():
    return [
        make_cell({"map": m, "n_vehicles": 8, "cav_penetration": 0.25, "style_mix": "D1"})
        for m in ("train-25", "train-50")
    ]


def test_ray_grid_writes_the_local_files(local_ray, tmp_path, capsys):
    spec, settings = parse_policy("cooperative"), EvalSettings(episode_steps=15)
    local = evaluate(spec, _cells(), 2, tmp_path / "local", settings, progress=False)
    remote = evaluate(
        spec, _cells(), 2, tmp_path / "ray", settings, progress=False, engine=RayEngine()
    )
    assert len(local.cells_run) == len(remote.cells_run) == 2
    for name in ("episodes.csv", "speeds.csv.gz"):
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes()
    # the CLI path: re-running skips the finished cells
    argv = ["eval", "--policy", "cooperative", "--episode-steps", "15", "--episodes", "2"]
    grid = tmp_path / "grid.toml"
    grid.write_text(
        '[product]\nmap = ["train-25", "train-50"]\nn_vehicles = [8]\ncav_penetration = [0.25]\n'
    )
    out = ["--grid", str(grid), "--out", str(tmp_path / "ray"), "--no-progress"]
    assert main([*argv, *out, "--engine", "ray"]) == 0
    assert "0 cells run, 2 already done" in capsys.readouterr().out


def test_ray_sweep_trains_like_a_local_run(local_ray, tmp_path):
    base = override(
        TrainConfig(),
        {
            "env.backend": "highway",
            "total_steps": 20,
            "n_envs": 1,
            "rollout_steps": 10,
            "minibatches": 1,  # 1 env x 10 steps: 1 sequence
            "epochs": 1,
            "device": "cpu",
            "env.scenario.n_vehicles": 8,
            "env.scenario.cav_penetration": 0.25,
            "env.sim.episode_steps": 10,
            "model.hidden_dim": 16,
            "model.gru_hidden": 16,
            "model.cross_dim": 16,
        },
    )
    configs = sweep_configs(base, ["mappo"], ["train-25"], [1, 2], tmp_path / "ray")
    runs = list(run_sweep(configs, engine="ray"))
    assert sorted((r.seed, r.status) for r in runs) == [(1, "trained"), (2, "trained")]
    (local,) = sweep_configs(base, ["mappo"], ["train-25"], [1], tmp_path / "local")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the Ray task (1 CPU): float sums depend on thread count
    try:
        (local_run,) = run_sweep([local], engine="local")
    finally:
        torch.set_num_threads(threads)

    def learning(record: dict) -> str:  # as JSON text: NaN (an unlogged mean) equals NaN
        return json.dumps({k: v for k, v in record.items() if k not in TIMING_KEYS})

    def records(run_dir):
        lines = (tmp_path / run_dir / "mappo-highway-train-25-s1" / "progress.jsonl").read_text()
        return [learning(json.loads(line)) for line in lines.splitlines()]

    assert records("ray") == records("local") and len(records("ray")) == 2
    assert records("ray")[-1] == learning(local_run.last)
    # finished runs are skipped
    assert {r.status for r in run_sweep(configs, engine="ray")} == {"skipped"}


def test_ray_option_without_ray_engine_is_an_error(capsys):
    argv = ["eval", "--policy", "pure-hdv", "--out", "x", "--ray-address", "auto"]
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == (
        "diacc: error: --ray-address / --ray-cpus need --engine ray"
    )

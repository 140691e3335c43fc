"""Progress that informs: the training bar's postfix and what ``train.log`` records."""

from __future__ import annotations

import re

from test_mappo import tiny_config

from diacc.config import TrainConfig, override
from diacc.console import TrainProgress
from diacc.learn.mappo import train
from diacc.runlog import config_digest


def test_postfix_reports_speed_and_collision_share_of_the_last_episodes():
    bar = TrainProgress(total_steps=100, done_steps=0, desc="t", enabled=False)
    assert bar.postfix(0.5) == "R=0.50 | no episode finished yet"
    crashed = {"mean_speed_mps": 10.0, "n_collisions": 1}
    clean = {"mean_speed_mps": 20.0, "n_collisions": 0}
    bar.update(10, 0.25, [crashed, clean, clean, clean])
    assert bar.postfix(0.25) == "R=0.25 | last 4 eps: 17.5 m/s, collisions 25 %"
    bar.update(10, 0.25, [clean] * TrainProgress.window)  # the window forgets the crash
    assert bar.postfix(0.25).endswith(f"last {TrainProgress.window} eps: 20.0 m/s, collisions 0 %")
    bar.close()


def test_config_digest_changes_with_the_config():
    cfg = TrainConfig()
    assert config_digest(cfg) == config_digest(TrainConfig())
    assert config_digest(cfg) != config_digest(override(cfg, {"lr": 1e-3}))
    assert re.fullmatch(r"[0-9a-f]{12}", config_digest(cfg))


def test_train_log_records_start_checkpoints_and_end(tmp_path):
    cfg = tiny_config(tmp_path, checkpoint_every=1)
    run = train(cfg, progress=False, stop_after_updates=1)
    train(cfg, resume=True, progress=False)
    lines = (run / "train.log").read_text().splitlines()
    messages = [line.split(" INFO ", 1)[1] for line in lines if " INFO " in line]
    digest = config_digest(cfg)
    assert messages == [
        f"start: {cfg.variant} in {run}, updates 1-1 of 2 (40 env steps each), config {digest}",
        "checkpoint: update 1, env step 40",
        messages[2],  # the collapse check of the updates since the last checkpoint
        messages[3],  # end, with its wall time
        f"start: {cfg.variant} in {run}, updates 2-2 of 2 (40 env steps each), config {digest}",
        "checkpoint: update 2, env step 80",
        messages[6],
        messages[7],
    ]
    assert messages[2].startswith("collapse check, updates 1-1: greedy ")
    assert messages[6].startswith("collapse check, updates 2-2: greedy ")  # resumed: from 2
    assert re.fullmatch(r"end: after update 1 of 2, env step 40, [0-9.]+ s", messages[3])
    assert re.fullmatch(r"end: after update 2 of 2, env step 80, [0-9.]+ s", messages[7])

"""Fingerprint of a tiny default training run: checks that options left at their
defaults change nothing (docs/concepts/learning-options.md).

Trains ``tests/test_mappo.py``'s ``tiny_config`` (2 envs, 80 steps, seed 1) into
OUT and prints the first 16 hex digits of the SHA-256 of the actor and critic
tensors (in name order), the last update's policy loss and its team reward.
Run it on two commits on the same machine; equal lines mean bit-identical runs::

    python benchmarks/speed/default_fingerprint.py /tmp/fingerprint
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from test_mappo import tiny_config  # noqa: E402

from diacc.learn.checkpoint import load_checkpoint  # noqa: E402
from diacc.learn.mappo import train  # noqa: E402


def main() -> None:
    out = Path(sys.argv[1])
    train(tiny_config(out), progress=False)
    checkpoint = load_checkpoint(out / "run" / "checkpoint.pt")
    digest = hashlib.sha256()
    for part in ("actor", "critic"):
        for _, tensor in sorted(checkpoint[part].items()):
            digest.update(tensor.numpy().tobytes())
    last = json.loads((out / "run" / "progress.jsonl").read_text().splitlines()[-1])
    print(digest.hexdigest()[:16], last["policy_loss"], last["team_reward"])


if __name__ == "__main__":
    main()

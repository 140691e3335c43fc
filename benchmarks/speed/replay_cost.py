"""CPU cost of the networks' sequence replay (forward + backward), two source trees side by side.

Small learner sizes (hidden 64), 20 critic sequences / 200 actor sequences of
10 steps, synthetic observations with 25 of 40 vehicle slots used. Each tree
runs in its own process, alternating, twice; each figure is the minimum CPU
time (``time.thread_time``) of 7 repeats, so that a loaded machine distorts
it little. Also prints how far the two trees' outputs on the same weights
differ::

    git worktree add /tmp/old <commit>
    python benchmarks/speed/replay_cost.py /tmp/old .
"""

import subprocess
import sys

code = r"""
import sys, time, torch, numpy as np
torch.set_num_threads(1)
from diacc.learn.models.registry import build_networks
from diacc.config import ModelConfig, ObservationConfig
from diacc.envs.observation import ObservationSpec
from diacc.learn.models.synthetic import random_critic_state, random_actor_obs
from diacc.learn.models.inputs import to_tensors
spec = ObservationSpec.from_config(ObservationConfig())
torch.manual_seed(0)
actor, critic = build_networks("diacc", ModelConfig(hidden_dim=64, gru_hidden=64), spec)
rng = np.random.default_rng(0)
st = random_critic_state(spec, (10, 20), rng, min_active=15)
st.node_mask[..., 25:] = False; st.neighbour_mask[..., 25:, :] = False
st = to_tensors(st)
ob = to_tensors(random_actor_obs(spec, (10, 200), rng))
starts = torch.zeros(10, 20, dtype=torch.bool); starts_a = torch.zeros(10, 200, dtype=torch.bool)
def c():
    v, _ = critic.forward_sequence(st, torch.zeros(20, 64), starts)
    v.sum().backward()
    return v
def a():
    logits, _ = actor.forward_sequence(ob, torch.zeros(200, 64), starts_a)
    logits.sum().backward()
    return logits
out = {}
for name, f in (("critic", c), ("actor", a)):
    r = f().detach()
    ts = []
    for _ in range(7):
        t = time.thread_time(); f(); ts.append(time.thread_time() - t)
    out[name] = (min(ts) * 1e3, r.flatten()[:50].tolist())
print(repr(out))
"""
res = {}
old_tree, new_tree = sys.argv[1], sys.argv[2]
for tree in (old_tree, new_tree, old_tree, new_tree):
    o = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=tree,
        env={"PYTHONPATH": tree, "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )
    if o.returncode:
        print(o.stderr[-2000:])
        sys.exit(1)
    r = eval(o.stdout.strip().splitlines()[-1])
    res.setdefault(tree, []).append(r)
    print(tree, {k: f"{v[0]:.1f} ms" for k, v in r.items()})
import numpy as np  # noqa: E402

for k in ("critic", "actor"):
    d = np.abs(np.array(res[old_tree][0][k][1]) - np.array(res[new_tree][0][k][1])).max()
    print(k, "max |old - new| on the same weights:", d)

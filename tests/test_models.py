"""Network properties: masking, invariances, attention, gradients, recurrence, registry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from diacc.config import VARIANTS, ModelConfig, ObservationConfig
from diacc.envs.observation import N_ACTIONS, ObservationSpec
from diacc.learn.models.errors import ModelError
from diacc.learn.models.gat import GraphAttention
from diacc.learn.models.inputs import to_tensors
from diacc.learn.models.itdr import ITDR, CIECCritic
from diacc.learn.models.mlp import MLPActor
from diacc.learn.models.recurrent import needed_rows
from diacc.learn.models.registry import build_networks
from diacc.learn.models.synthetic import random_actor_obs, random_critic_state
from diacc.learn.models.taie import TAIE, DIADMActor

CFG = ModelConfig(hidden_dim=32, gat_heads=2, cross_heads=4, cross_dim=16, gru_hidden=24)
SPEC = ObservationSpec.from_config(ObservationConfig())
ATOL = 1e-5


def _actor_obs(batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    return to_tensors(random_actor_obs(SPEC, (batch,), np.random.default_rng(seed)))


def _critic_state(batch: int, seed: int = 0, min_active: int = 3) -> dict[str, torch.Tensor]:
    state = random_critic_state(SPEC, (batch,), np.random.default_rng(seed), min_active=min_active)
    return to_tensors(state)


def _seeded(cls, *args):
    torch.manual_seed(0)
    return cls(*args)


# ---------------------------------------------------------------- GAT layer
def _reference_gat(layer: GraphAttention, hq, hk, mask):
    """Per-row loop implementation of the paper's equations, for comparison."""
    w = layer.proj.weight.detach()
    out = torch.zeros(hq.shape[0], layer.out_features)
    for b in range(hq.shape[0]):
        nodes = [hq[b]] + [hk[b, j] for j in range(hk.shape[1]) if mask[b, j]]
        heads = []
        for h in range(layer.heads):
            wh = w[h * layer.head_dim : (h + 1) * layer.head_dim]
            wi = wh @ hq[b]
            e = torch.stack(
                [
                    torch.nn.functional.leaky_relu(
                        torch.dot(layer.att_query[h], wi) + torch.dot(layer.att_key[h], wh @ x), 0.2
                    )
                    for x in nodes
                ]
            )
            alpha = torch.softmax(e, 0)
            heads.append(sum(a * (wh @ x) for a, x in zip(alpha, nodes, strict=True)))
        agg = torch.cat(heads) if layer.concat else torch.stack(heads).mean(0)
        out[b] = torch.nn.functional.elu(agg)
    return out


@pytest.mark.parametrize("concat", [False, True])
def test_gat_matches_the_paper_equations(concat):
    torch.manual_seed(1)
    layer = GraphAttention(5, 4, heads=3, concat=concat)
    hq, hk = torch.randn(6, 5), torch.randn(6, 7, 5)
    mask = torch.rand(6, 7) < 0.6
    with torch.no_grad():
        got = layer(hq[:, None], hk[:, None], mask[:, None])[:, 0]
        want = _reference_gat(layer, hq, hk, mask)
    assert got.shape == (6, 12 if concat else 4)
    torch.testing.assert_close(got, want, atol=ATOL, rtol=1e-4)


def test_gat_ignores_padding_even_inf_and_nan():
    torch.manual_seed(2)
    layer = GraphAttention(5, 4, heads=2)
    hq, hk = torch.randn(4, 1, 5), torch.randn(4, 1, 3, 5)
    mask = torch.tensor(
        [[True, False, True], [False, False, False], [True, True, True], [False, True, False]]
    )[:, None]
    base = layer(hq, hk, mask)
    padded_keys = torch.cat([hk, torch.randn(4, 1, 4, 5) * 1e3], dim=2)
    padded_keys[:, :, 3:5] = float("nan")
    padded_keys[0, 0, 1] = float("inf")  # an existing masked slot
    padded_mask = torch.cat([mask, torch.zeros(4, 1, 4, dtype=torch.bool)], dim=2)
    torch.testing.assert_close(layer(hq, padded_keys, padded_mask), base, atol=0, rtol=0)


def test_gat_fully_masked_rows_give_zeros_and_finite_gradients():
    torch.manual_seed(3)
    layer = GraphAttention(5, 4, heads=2, self_loop=False)
    hq = torch.randn(3, 1, 5, requires_grad=True)
    hk = torch.randn(3, 1, 6, 5, requires_grad=True)
    mask = torch.zeros(3, 1, 6, dtype=torch.bool)
    mask[2, 0, :2] = True
    out = layer(hq, hk, mask)
    assert torch.equal(out[:2], torch.zeros_like(out[:2]))
    assert out[2].abs().sum() > 0
    out.sum().backward()
    for p in [hq, hk, *layer.parameters()]:
        assert torch.isfinite(p.grad).all()
    assert torch.equal(hk.grad[:2], torch.zeros_like(hk.grad[:2]))


def test_gat_graph_form_equals_gathered_star_form():
    torch.manual_seed(4)
    layer = GraphAttention(6, 5, heads=2)
    state = _critic_state(3)
    h = torch.randn(3, SPEC.max_vehicles, 6)
    nb, em, nm = state["neighbours"], state["neighbour_mask"], state["node_mask"]
    graph = layer.forward_graph(h, nb, em, nm)
    keys = torch.stack([h[b][nb[b]] for b in range(3)])  # (B, N, K, F)
    star = layer(h, keys, em & nm[..., None], query_mask=nm)
    torch.testing.assert_close(graph, star, atol=ATOL, rtol=1e-4)
    assert torch.equal(graph[~nm], torch.zeros_like(graph[~nm]))
    # An edge that claims to exist but points at a padded vehicle is ignored.
    assert (~nm).any(-1).all(), "test needs a padded slot in every state"
    first_free = nm.sum(-1)  # (B,) index of the first padded slot
    dangling_nb, dangling_em = nb.clone(), em.clone()
    dangling_nb[:, 0, -1], dangling_em[:, 0, -1] = first_free, True
    dangling = layer.forward_graph(h, dangling_nb, dangling_em, nm)
    em_off = em.clone()
    em_off[:, 0, -1] = False
    torch.testing.assert_close(
        dangling, layer.forward_graph(h, nb, em_off, nm), atol=ATOL, rtol=1e-5
    )


# ---------------------------------------------------------------- padding invariance
def _pad_actor(obs, extra: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    out = dict(obs)
    m, k = obs["hdv_mask"].shape
    for nodes, mask in (("hdv_nodes", "hdv_mask"), ("cav_nodes", "cav_mask")):
        noisy = (
            obs[nodes]
            + 50 * torch.randn(obs[nodes].shape, generator=g) * ~obs[mask][..., None, None]
        )
        junk = 50 * torch.randn((m, extra, *obs[nodes].shape[2:]), generator=g)
        out[nodes] = torch.cat([noisy, junk], 1)
        out[mask] = torch.cat([obs[mask], torch.zeros(m, extra, dtype=torch.bool)], 1)
    junk_actions = torch.randint(0, N_ACTIONS, (m, k + extra), generator=g)
    out["cav_prev_action"] = torch.where(
        out["cav_mask"],
        torch.cat([obs["cav_prev_action"], torch.zeros(m, extra, dtype=torch.long)], 1),
        junk_actions,
    )
    return out


@pytest.mark.parametrize("concat_heads", [False, True])
def test_taie_ignores_extra_and_altered_padding(concat_heads):
    obs = _actor_obs(64)
    taie = _seeded(TAIE, dataclasses.replace(CFG, taie_concat_heads=concat_heads), SPEC)
    assert taie(obs).shape == (64, CFG.hidden_dim)
    with torch.no_grad():
        torch.testing.assert_close(
            taie(_pad_actor(obs, 3, seed=5)), taie(obs), atol=ATOL, rtol=1e-5
        )


def _pad_critic(state, extra: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    b, n, k = state["neighbours"].shape
    out = dict(state)
    out["nodes"] = torch.cat([state["nodes"], 50 * torch.randn(b, extra, 6, generator=g)], 1)
    out["node_mask"] = torch.cat([state["node_mask"], torch.zeros(b, extra, dtype=torch.bool)], 1)
    junk_index = torch.randint(0, n + extra, (b, n + extra, k), generator=g)
    out["neighbours"] = torch.where(
        torch.cat([state["neighbour_mask"], torch.zeros(b, extra, k, dtype=torch.bool)], 1),
        torch.cat([state["neighbours"], junk_index[:, n:]], 1),
        junk_index,
    )
    # Padded vehicles' own neighbour lists claim edges: node_mask must still exclude them.
    out["neighbour_mask"] = torch.cat(
        [state["neighbour_mask"], torch.ones(b, extra, k, dtype=torch.bool)], 1
    )
    return out


def test_itdr_ignores_extra_padded_vehicles():
    state = _critic_state(6)
    itdr = _seeded(ITDR, CFG, SPEC)
    with torch.no_grad():
        padded = _pad_critic(state, 7, seed=6)
        torch.testing.assert_close(itdr(padded), itdr(state), atol=ATOL, rtol=1e-5)
        torch.testing.assert_close(
            itdr.node_features(padded)[:, : SPEC.max_vehicles],
            itdr.node_features(state),
            atol=ATOL,
            rtol=1e-5,
        )


# ---------------------------------------------------------------- permutations
def test_actor_distribution_ignores_neighbour_order():
    obs = _actor_obs(32, seed=7)
    actor = _seeded(DIADMActor, CFG, SPEC)
    perm = torch.randperm(SPEC.n_neighbours, generator=torch.Generator().manual_seed(0))
    shuffled = dict(obs)
    for key in ("hdv_nodes", "hdv_mask", "cav_nodes", "cav_mask", "cav_prev_action"):
        shuffled[key] = obs[key][:, perm]
    hidden, start = torch.randn(32, CFG.gru_hidden), torch.zeros(32)
    with torch.no_grad():
        logits, h = actor(obs, hidden, start)
        logits_s, h_s = actor(shuffled, hidden, start)
    torch.testing.assert_close(logits_s, logits, atol=ATOL, rtol=1e-5)
    torch.testing.assert_close(h_s, h, atol=ATOL, rtol=1e-5)


def test_critic_is_equivariant_in_nodes_and_invariant_in_value():
    state = _critic_state(4, seed=8)
    critic = _seeded(CIECCritic, CFG, SPEC)
    n = SPEC.max_vehicles
    perm = torch.randperm(
        n, generator=torch.Generator().manual_seed(1)
    )  # new slot i holds old perm[i]
    inverse = torch.argsort(perm)  # old index -> new index
    permuted = dict(state)
    for key in ("nodes", "node_mask", "neighbour_mask"):
        permuted[key] = state[key][:, perm]
    permuted["neighbours"] = inverse[state["neighbours"][:, perm]]
    hidden, start = torch.randn(4, CFG.gru_hidden), torch.zeros(4)
    with torch.no_grad():
        nodes = critic.encoder.node_features(state)
        nodes_p = critic.encoder.node_features(permuted)
        value, _ = critic(state, hidden, start)
        value_p, _ = critic(permuted, hidden, start)
    torch.testing.assert_close(nodes_p, nodes[:, perm], atol=ATOL, rtol=1e-5)
    torch.testing.assert_close(value_p, value, atol=ATOL, rtol=1e-5)


# ---------------------------------------------------------------- cross-attention
def test_cross_attention_is_not_degenerate():
    state = _critic_state(5, seed=9, min_active=10)
    critic = _seeded(CIECCritic, CFG, SPEC)
    hidden, start = torch.zeros(5, CFG.gru_hidden), torch.zeros(5)
    with torch.no_grad():
        value, _ = critic(state, hidden, start)
        features, weights = critic.encoder(state, return_attention=True)
        assert weights.shape == (5, CFG.cross_heads, SPEC.max_vehicles)
        mask = state["node_mask"][:, None, :].expand_as(weights)
        torch.testing.assert_close(weights.sum(-1), torch.ones(5, CFG.cross_heads))
        assert torch.equal(weights[~mask], torch.zeros_like(weights[~mask]))
        spread = weights.masked_fill(~mask, -1).amax(-1) - weights.masked_fill(~mask, 2).amin(-1)
        assert (spread > 1e-4).all(), "attention weights are (nearly) uniform over the keys"
        assert torch.equal(critic.encoder.cross.last_attention, weights)
        changed = dict(state)
        changed["nodes"] = state["nodes"].clone()
        changed["nodes"][:, 4] += 1.0  # vehicle 4 is active in every state (min_active=10)
        value_changed, _ = critic(changed, hidden, start)
    assert ((value_changed - value).abs() > 1e-6).all()


# ---------------------------------------------------------------- empty graphs
def test_no_nan_without_neighbours_or_vehicles():
    torch.manual_seed(10)
    obs = _actor_obs(8, seed=10)
    obs["hdv_mask"] = torch.zeros_like(obs["hdv_mask"])
    obs["cav_mask"] = torch.zeros_like(obs["cav_mask"])
    obs["lane_mask"] = torch.zeros_like(obs["lane_mask"])
    state = _critic_state(3, seed=10)
    for key in ("node_mask", "neighbour_mask", "lane_mask"):
        state[key] = torch.zeros_like(state[key])
    for variant in VARIANTS:
        actor, critic = build_networks(variant, CFG, SPEC)
        logits, _ = actor(obs, torch.zeros(8, CFG.gru_hidden), torch.ones(8))
        value, _ = critic(state, torch.zeros(3, CFG.gru_hidden), torch.ones(3))
        (logits.sum() + value.sum()).backward()
        assert torch.isfinite(logits).all() and torch.isfinite(value).all()
        for name, p in [*actor.named_parameters(), *critic.named_parameters()]:
            assert p.grad is None or torch.isfinite(p.grad).all(), f"{variant}: NaN grad in {name}"
    itdr = _seeded(ITDR, CFG, SPEC)
    _, weights = itdr(state, return_attention=True)
    assert torch.equal(weights, torch.zeros_like(weights))
    assert torch.equal(itdr.node_features(state), torch.zeros(3, SPEC.max_vehicles, CFG.hidden_dim))


# ---------------------------------------------------------------- gradients and recurrence
@pytest.mark.parametrize("variant", VARIANTS)
def test_gradients_reach_every_parameter(variant):
    torch.manual_seed(11)
    actor, critic = build_networks(variant, CFG, SPEC)
    obs = to_tensors(random_actor_obs(SPEC, (2, 16), np.random.default_rng(11)))  # (T, B, ...)
    state = to_tensors(random_critic_state(SPEC, (2, 4), np.random.default_rng(12), min_active=5))
    logits, _ = actor.forward_sequence(obs, torch.zeros(16, CFG.gru_hidden), torch.zeros(2, 16))
    value, _ = critic.forward_sequence(state, torch.zeros(4, CFG.gru_hidden), torch.zeros(2, 4))
    dist = torch.distributions.Categorical(logits=logits)
    loss = (
        -(dist.log_prob(torch.zeros_like(logits[..., 0], dtype=torch.long))).mean()
        - dist.entropy().mean()
        + (value - 1.0).pow(2).mean()
    )
    loss.backward()
    for name, p in [*actor.named_parameters(), *critic.named_parameters()]:
        assert p.grad is not None and p.grad.abs().sum() > 0, f"{variant}: no gradient for {name}"


def test_episode_start_resets_the_hidden_state():
    obs = _actor_obs(6, seed=13)
    actor = _seeded(DIADMActor, CFG, SPEC)
    stale = torch.randn(6, CFG.gru_hidden)
    start = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    with torch.no_grad():
        logits, h = actor(obs, stale, start)
        logits0, h0 = actor(obs, torch.zeros(6, CFG.gru_hidden), start)
    torch.testing.assert_close(h[:3], h0[:3], atol=0, rtol=0)
    torch.testing.assert_close(logits[:3], logits0[:3], atol=0, rtol=0)
    assert (h[3:] - h0[3:]).abs().amax() > 1e-3  # no reset: the carried state matters


@pytest.mark.parametrize(
    "variant, input_norm", [("mappo", False), ("diacc", False), ("diacc", True)]
)
def test_sequence_replay_equals_step_by_step(variant, input_norm):
    actor, critic = build_networks(
        variant, dataclasses.replace(CFG, gru_input_norm=input_norm), SPEC
    )
    rng = np.random.default_rng(14)
    obs = to_tensors(random_actor_obs(SPEC, (4, 5), rng))
    state = to_tensors(random_critic_state(SPEC, (4, 2), rng))
    for net, inputs, batch in ((actor, obs, 5), (critic, state, 2)):
        starts = torch.zeros(4, batch)
        starts[2, 0] = 1.0
        h0 = torch.randn(batch, CFG.gru_hidden)
        with torch.no_grad():
            seq, h_seq = net.forward_sequence(inputs, h0, starts)
            h, outs = h0, []
            for t in range(4):
                out, h = net({k: v[t] for k, v in inputs.items()}, h, starts[t])
                outs.append(out)
        # Rows of agents off the road that reach no loss are not encoded in the replay.
        needed = needed_rows(inputs, starts)
        rows = slice(None) if needed is None else needed.view(4, batch)
        torch.testing.assert_close(seq[rows], torch.stack(outs)[rows], atol=ATOL, rtol=1e-5)
        last = slice(None) if needed is None else rows[-1]
        torch.testing.assert_close(h_seq[last], h[last], atol=ATOL, rtol=1e-5)


def test_replay_skips_only_rows_that_reach_no_loss():
    """An actor replay encodes the alive rows and the dead rows whose GRU state an alive
    row inherits (no reset between): garbage in any other row changes no alive output."""
    actor, _ = build_networks("diacc", CFG, SPEC)
    obs = to_tensors(random_actor_obs(SPEC, (6, 4), np.random.default_rng(3)))
    alive = torch.tensor([[1, 1, 0, 1]] * 6, dtype=torch.bool)
    alive[3:, 0] = False  # left the road at t = 3: rows 3-5 of agent 0 are skipped
    alive[:4, 1] = False  # dead, then alive at t = 4 with no reset: rows 0-3 carry its state
    alive[:2, 3] = False  # dead, then a new CAV at t = 2 (reset): rows 0-1 are skipped
    starts = torch.zeros(6, 4)
    starts[2, 3] = 1.0
    obs["alive"] = alive
    needed = needed_rows(obs, starts).view(6, 4)
    want = alive.clone()
    want[:4, 1] = True
    assert torch.equal(needed, want)
    h0 = torch.zeros(4, CFG.gru_hidden)
    with torch.no_grad():
        clean, _ = actor.forward_sequence(obs, h0, starts)
        noisy = {k: v.clone() for k, v in obs.items()}
        noisy["ego_hist"][~needed] = 1e6  # only rows that reach no loss
        dirty, _ = actor.forward_sequence(noisy, h0, starts)
    torch.testing.assert_close(dirty[alive], clean[alive], rtol=0, atol=0)


# ---------------------------------------------------------------- registry and inputs
def test_registry_pairs_and_determinism():
    kinds = {v: tuple(type(n).__name__ for n in build_networks(v, CFG, SPEC)) for v in VARIANTS}
    assert kinds == {
        "mappo": ("MLPActor", "MLPCritic"),
        "mappo-iadm": ("DIADMActor", "MLPCritic"),
        "diacc-nopsar": ("DIADMActor", "CIECCritic"),
        "diacc": ("DIADMActor", "CIECCritic"),
        "mappo-psar": ("MLPActor", "MLPCritic"),
    }
    torch.manual_seed(0)
    a1, _ = build_networks("diacc", CFG, SPEC)
    torch.manual_seed(0)
    a2, _ = build_networks("diacc", CFG, SPEC)
    for p1, p2 in zip(a1.parameters(), a2.parameters(), strict=True):
        assert torch.equal(p1, p2)
    head = a1.head.weight  # orthogonal with gain 0.01: rows have norm 0.01
    torch.testing.assert_close(head.norm(dim=1), torch.full((N_ACTIONS,), 0.01))
    with pytest.raises(ModelError, match="unknown variant 'qmix'"):
        build_networks("qmix", CFG, SPEC)


def test_to_tensors_keeps_dtypes_and_any_batch_axes():
    rng = np.random.default_rng(15)
    obs = to_tensors(random_actor_obs(SPEC, (3, 4), rng))
    assert obs["hdv_nodes"].dtype == torch.float32 and obs["hdv_nodes"].shape[:2] == (3, 4)
    assert obs["hdv_mask"].dtype == torch.bool and obs["action_memory"].dtype == torch.long
    bad = random_critic_state(SPEC, (2,), rng)
    bad.neighbours[0, 0, 0], bad.neighbour_mask[0, 0, 0] = SPEC.max_vehicles, True
    with pytest.raises(ModelError, match="outside"):
        to_tensors(bad)
    with pytest.raises(ModelError, match="unsupported dtype"):
        to_tensors({"x": np.array(["a"])})


def test_bad_inputs_raise_one_line_errors():
    actor = _seeded(MLPActor, CFG, SPEC)
    obs = _actor_obs(4)
    with pytest.raises(ModelError, match="lacks fields"):
        actor(
            {k: v for k, v in obs.items() if k != "road"},
            torch.zeros(4, CFG.gru_hidden),
            torch.zeros(4),
        )
    with pytest.raises(ModelError, match="leading shape"):
        actor(obs, torch.zeros(5, CFG.gru_hidden), torch.zeros(5))
    spec = ObservationSpec.from_config(ObservationConfig(n_neighbours=4))
    small = to_tensors(random_actor_obs(spec, (4,), np.random.default_rng(0)))
    with pytest.raises(ModelError, match="built for"):
        actor(small, torch.zeros(4, CFG.gru_hidden), torch.zeros(4))
    with pytest.raises(ModelError, match="multiple of cross_heads"):
        build_networks("diacc", ModelConfig(cross_dim=30, cross_heads=8), SPEC)
    with pytest.raises(ModelError, match="multiple of gat_heads"):
        TAIE(ModelConfig(hidden_dim=30, gat_heads=4, taie_concat_heads=True), SPEC)


def test_models_benchmark_runs_small():
    from diacc.experiments.bench.models import run

    figures = run("cpu", n_envs=2, n_cavs=3, rollout_steps=4, chunk_len=2, repeats=1)
    assert set(figures["params"]) == set(VARIANTS)
    for variant in VARIANTS:
        assert figures["step_ms"][variant] > 0 and figures["update_s"][variant] > 0


def test_every_variant_runs_on_builder_observations():
    """Real ObservationBuilder output (not synthetic) fits every network, batch of 2 envs."""
    from helpers import make_state

    from diacc.config import ObservationConfig
    from diacc.envs.observation import ActorObs, CriticState, ObservationBuilder
    from diacc.sim.maps import load_map

    road, obs_cfg = load_map("train-25"), ObservationConfig()
    rng = np.random.default_rng(16)
    actor_obs, critic_states = [], []
    for n_vehicles in (12, 1):  # a busy road and a lone CAV without neighbours
        x_m = np.sort(rng.uniform(0.0, 400.0, n_vehicles))
        state = make_state(
            x_m, rng.integers(0, 4, n_vehicles), is_cav=np.arange(n_vehicles) % 2 == 0
        )
        builder = ObservationBuilder(road, obs_cfg, episode_steps=100)
        builder.reset(state)
        cavs = np.flatnonzero(state.is_cav[0])[None, :1]  # (1, 1): state is a batch of one
        memory = rng.integers(0, N_ACTIONS, (1, 1, 2))
        actor_obs.append(
            builder.actor(cavs, memory, np.zeros((1, n_vehicles), np.int64)).unbatched(0)
        )
        critic_states.append(builder.critic().unbatched(0))
    obs, state = (
        to_tensors(ActorObs.stack(actor_obs)),
        to_tensors(CriticState.stack(critic_states)),
    )  # (2, 1, ...), (2, ...)
    obs = {k: v[:, 0] for k, v in obs.items()}  # one CAV slot per env -> (2, ...)
    assert not obs["hdv_mask"][1].any() and not obs["cav_mask"][1].any()
    spec = ObservationSpec.from_config(obs_cfg)
    for variant in VARIANTS:
        actor, critic = build_networks(variant, CFG, spec)
        logits, _ = actor(obs, torch.zeros(2, CFG.gru_hidden), torch.ones(2))
        value, _ = critic(state, torch.zeros(2, CFG.gru_hidden), torch.ones(2))
        assert logits.shape == (2, N_ACTIONS) and value.shape == (2,)
        assert torch.isfinite(logits).all() and torch.isfinite(value).all()


# ---------------------------------------------------------------- cheaper forms, same maths
def test_cross_attention_matches_the_per_head_formula():
    """The fused K/V product and elementwise scores equal softmax(q k^T / sqrt(d)) v per head."""
    from diacc.learn.models.attention import CrossAttention

    torch.manual_seed(5)
    layer = CrossAttention(12, 6, 16, 4)
    query, keys = torch.randn(3, 12), torch.randn(3, 9, 6)
    mask = torch.rand(3, 9) < 0.6
    mask[0] = False  # no keys at all: zeros
    mask[1, 0] = True
    with torch.no_grad():
        got, weights = layer(query, keys, mask, return_attention=True)
        want = torch.zeros(3, 16)
        for b in range(1, 3):
            heads = []
            for h in range(4):
                cut = slice(4 * h, 4 * h + 4)
                q = layer.q(query[b])[cut]
                k, v = layer.k(keys[b, mask[b]])[:, cut], layer.v(keys[b, mask[b]])[:, cut]
                heads.append(torch.softmax(k @ q / 2.0, 0) @ v)
            want[b] = layer.out(torch.cat(heads))
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)
    assert weights.shape == (3, 4, 9) and torch.equal(weights[0], torch.zeros(4, 9))


def test_trimming_padded_node_slots_changes_no_output_or_gradient(monkeypatch):
    """ITDR cuts the node slots behind the last vehicle; outputs and gradients stay the same."""
    import diacc.learn.models.itdr as itdr

    state = _critic_state(6, seed=11, min_active=3)
    state["node_mask"][:, 20:] = False  # vehicles in the first 20 of 40 slots only
    state["neighbour_mask"] &= state["node_mask"][..., None]
    trimmed = itdr.trim_padded_nodes(state)
    assert trimmed["nodes"].shape[1] == int(state["node_mask"].nonzero()[:, 1].max()) + 1 <= 20

    def value_and_grads():
        critic = _seeded(CIECCritic, CFG, SPEC)
        value, _ = critic(state, torch.zeros(6, CFG.gru_hidden), torch.zeros(6))
        value.sum().backward()
        return value.detach(), [p.grad.clone() for p in critic.parameters()]

    value, grads = value_and_grads()
    monkeypatch.setattr(itdr, "trim_padded_nodes", lambda s: s)
    value_full, grads_full = value_and_grads()
    torch.testing.assert_close(value, value_full, atol=1e-6, rtol=1e-5)
    for g, g_full in zip(grads, grads_full, strict=True):
        torch.testing.assert_close(g, g_full, atol=1e-6, rtol=1e-5)


# ---------------------------------------------------------------- hand-written backward passes
def _autograd_star_pool(q, x, valid, u_q, u_k, slope):
    """StarPool's maths through autograd's own ops (the reference for its backward)."""
    from diacc.learn.models.layers import masked_softmax

    z = (q @ u_q)[:, :, None] + torch.einsum("mkf,fh->mhk", x, u_k)  # (M, H, K)
    logits = torch.nn.functional.leaky_relu(z, slope)
    alpha = masked_softmax(logits, valid[:, None, :], dim=-1)
    return alpha @ x


def test_star_pool_backward_equals_autograd_in_float64():
    """StarPool's written-out backward gives autograd's gradients (float64: to 1e-12)."""
    from diacc.learn.models.gat import StarPool

    g = torch.Generator().manual_seed(6)
    m, k, f, h = 9, 7, 5, 3
    leaves = [torch.randn(m, f, generator=g, dtype=torch.float64)]  # q
    leaves.append(torch.randn(m, k, f, generator=g, dtype=torch.float64))  # x
    valid = torch.rand(m, k, generator=g) < 0.6
    valid[0] = False  # a row without keys: zeros, zero gradient
    leaves[1] = leaves[1] * valid[..., None]
    leaves += [torch.randn(f, h, generator=g, dtype=torch.float64) for _ in range(2)]  # u_q, u_k
    weights = torch.randn(m, h, f, generator=g, dtype=torch.float64)
    grads = []
    for fn in (lambda *a: StarPool.apply(*a, 0.2)[0], lambda *a: _autograd_star_pool(*a, 0.2)):
        inputs = [t.clone().requires_grad_(True) for t in leaves]
        out = fn(inputs[0], inputs[1], valid, inputs[2], inputs[3])
        (out * weights).sum().backward()
        grads.append((out.detach(), [t.grad for t in inputs]))
    (out_a, grads_a), (out_b, grads_b) = grads
    torch.testing.assert_close(out_a, out_b, rtol=0, atol=1e-12)
    for a, b in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert torch.equal(out_a[0], torch.zeros_like(out_a[0]))


def test_gru_step_equals_torch_gru_cell():
    """The chunked replay's GRU (input half precomputed) is nn.GRUCell's maths."""
    from diacc.learn.models.recurrent import gru_step

    torch.manual_seed(7)
    cell = torch.nn.GRUCell(6, 5)
    x, h = torch.randn(4, 6), torch.randn(4, 5)
    gates = torch.nn.functional.linear(x, cell.weight_ih, cell.bias_ih)
    torch.testing.assert_close(gru_step(gates, h, cell), cell(x, h), rtol=0, atol=1e-6)


def test_star_pool_under_bf16_autocast_returns_gradients_in_input_dtypes():
    """update_bf16 runs the networks under autocast: StarPool's backward must cope."""
    torch.manual_seed(8)
    layer = GraphAttention(8, 8, 4)
    query = torch.randn(5, 8, requires_grad=True)
    mask = torch.rand(5, 6) > 0.3
    keys = (torch.randn(5, 6, 8) * mask[..., None]).requires_grad_(True)
    with torch.autocast("cpu", torch.bfloat16):
        out = layer(query, keys, mask, keys_zeroed=True)
    out.float().sum().backward()
    assert out.dtype == torch.bfloat16 and query.grad.dtype == keys.grad.dtype == torch.float32
    assert all(torch.isfinite(p.grad).all() for p in (query, keys, *layer.parameters()))


def test_the_gru_input_norm_is_an_option_that_adds_parameters_only_when_on():
    """Off (the default), a network's parameters are those of every checkpoint trained
    before the option; on, every GRU reads layer-normalised features whatever their
    scale, so a common offset in the features cannot pin the GRU's units."""
    plain, _ = build_networks("diacc", CFG, SPEC)
    normed, critic = build_networks("diacc", dataclasses.replace(CFG, gru_input_norm=True), SPEC)
    assert not any("input_norm" in name for name in plain.state_dict())
    assert {"input_norm.weight", "input_norm.bias"} <= set(normed.state_dict())
    assert "input_norm.weight" in critic.state_dict()
    features = torch.randn(7, normed.encoder.out_dim)
    shifted = normed.input_norm(3.0 * features + 5.0)
    torch.testing.assert_close(shifted, normed.input_norm(features), atol=1e-4, rtol=1e-4)

"""The CNMP model, its training-step sampler and the in-memory API."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lerobot_cnmp.api import CNMPModel, Condition, pad_demos
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig, MixtureConfig
from lerobot_cnmp.model.cnmp import CNMP, Context, Episodes, Targets
from lerobot_cnmp.model.mixture import MixtureCNMP, mixture_of, n_experts
from lerobot_cnmp.model.numpy_cnmp import NumpyCNMP
from lerobot_cnmp.model.sampling import sample_context_and_targets


def toy_demos(n=8, t=50, seed=0):
    """Two modes (bump up / bump down) with varied amplitude: [n, t, 2]."""
    rng = np.random.default_rng(seed)
    tau = np.linspace(0, 1, t)
    out = []
    for i in range(n):
        s = 1 if i % 2 == 0 else -1
        h = s * rng.uniform(0.3, 0.5)
        out.append(np.stack([tau, h * np.sin(np.pi * tau)], 1))
    return np.stack(out).astype(np.float32)


def random_context(b=3, n=5, d=2, g=0, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return Context(
        phase=torch.rand(b, n, generator=gen),
        values=torch.randn(b, n, d, generator=gen),
        mask=(torch.rand(b, n, d, generator=gen) < 0.7).float(),
        valid=torch.ones(b, n, dtype=torch.bool),
        task_params=torch.randn(b, g, generator=gen) if g else None,
    )


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return CNMP(sm_dim=2, task_dim=1, encoder_layers=(32, 32), decoder_layers=(32, 32)).eval()


def test_shapes_and_positive_std(net):
    ctx = random_context(g=1)
    mean, std = net(ctx, torch.rand(3, 7))
    assert mean.shape == (3, 7, 2) and std.shape == (3, 7, 2)
    assert bool((std >= net.min_std).all())


@pytest.mark.parametrize("task_dim,freqs", [(0, 0), (2, 0), (1, 3)])
def test_fast_path_equals_the_plain_networks(task_dim, freqs):
    """encode/decode run the layers without module calls and split Q's first layer; the result must be the
    plain E(·) and Q([t, γ, r]) of the paper's equations."""
    torch.manual_seed(1)
    m = CNMP(sm_dim=2, task_dim=task_dim, encoder_layers=(16, 8), decoder_layers=(16, 16), phase_frequencies=freqs)
    ctx = random_context(b=3, n=5, g=task_dim)
    q = torch.rand(3, 6)
    parts = [m.phase_features(ctx.phase)] + ([ctx.task_params[:, None].expand(-1, 5, -1)] if task_dim else [])
    r_i = m.encoder(torch.cat(parts + [ctx.values * ctx.mask, ctx.mask], -1))
    torch.testing.assert_close(m.encode(ctx), r_i)
    r = r_i.mean(1)
    parts = [m.phase_features(q)] + ([ctx.task_params[:, None].expand(-1, 6, -1)] if task_dim else [])
    out = m.decoder(torch.cat(parts + [r[:, None].expand(-1, 6, -1)], -1))
    mean, std = m(ctx, q)
    torch.testing.assert_close(mean, out[..., :2])
    torch.testing.assert_close(std, m.min_std + torch.nn.functional.softplus(out[..., 2:]))


def test_context_permutation_invariance(net):
    ctx = random_context(g=1)
    q = torch.rand(3, 4)
    perm = torch.tensor([4, 2, 0, 3, 1])
    shuffled = Context(ctx.phase[:, perm], ctx.values[:, perm], ctx.mask[:, perm], ctx.valid[:, perm], ctx.task_params)
    a, b = net(ctx, q), net(shuffled, q)
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])


def test_padding_invariance(net):
    ctx = random_context(g=1)
    q = torch.rand(3, 4)
    pad = 6
    padded = Context(
        torch.cat([ctx.phase, torch.rand(3, pad)], 1),
        torch.cat([ctx.values, 100 * torch.randn(3, pad, 2)], 1),
        torch.cat([ctx.mask, torch.ones(3, pad, 2)], 1),
        torch.cat([ctx.valid, torch.zeros(3, pad, dtype=torch.bool)], 1),
        ctx.task_params,
    )
    a, b = net(ctx, q), net(padded, q)
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])
    # Padded queries do not change the loss either.
    targets = Targets(q, torch.randn(3, 4, 2), torch.ones(3, 4, dtype=torch.bool))
    loss = CNMP.nll(*a, targets)
    q2 = torch.cat([q, torch.rand(3, 5)], 1)
    m2, s2 = net(ctx, q2)
    t2 = Targets(q2, torch.cat([targets.values, 50 * torch.randn(3, 5, 2)], 1),
                 torch.cat([targets.valid, torch.zeros(3, 5, dtype=torch.bool)], 1))
    torch.testing.assert_close(loss, CNMP.nll(m2, s2, t2))


def test_masked_dims_do_not_matter(net):
    """A dimension that is not observed (mask 0) has no influence, whatever its value."""
    ctx = random_context(g=1)
    other = Context(ctx.phase, torch.where(ctx.mask > 0, ctx.values, torch.full_like(ctx.values, 1e3)),
                    ctx.mask, ctx.valid, ctx.task_params)
    q = torch.rand(3, 4)
    torch.testing.assert_close(net(ctx, q)[0], net(other, q)[0])


def test_sampler_respects_padding_and_counts():
    b, w, d = 64, 30, 2
    values = torch.randn(b, w, d)
    lengths = torch.randint(1, w + 1, (b,))
    valid = torch.arange(w)[None] < lengths[:, None]
    phase = torch.rand(b, w)
    values[~valid] = float("nan")  # a padded entry must never be drawn
    ctx, tgt = sample_context_and_targets(Episodes(values, phase, valid), n_max=5, m_max=7,
                                          partial_obs_prob=0.5, generator=torch.Generator().manual_seed(0))
    assert ctx.values.shape == (b, 5, d) and tgt.values.shape == (b, 7, d)
    assert not torch.isnan(ctx.values[ctx.valid]).any() and not torch.isnan(tgt.values[tgt.valid]).any()
    n_ctx, n_tgt = ctx.valid.sum(1), tgt.valid.sum(1)
    assert bool((n_ctx >= 1).all()) and bool((n_ctx <= lengths.clamp(max=5)).all())
    assert bool((n_tgt >= 1).all()) and bool((n_tgt <= lengths.clamp(max=7)).all())
    assert set(n_ctx.tolist()) == {1, 2, 3, 4, 5}  # the whole range 1..n_max is drawn
    assert bool((ctx.mask.sum(-1) >= 1).all())  # partial observations are never empty
    assert bool((ctx.mask.sum(-1) < d).any())


def test_sampler_rejects_empty_episode():
    valid = torch.zeros(2, 5, dtype=torch.bool)
    valid[0, 0] = True
    with pytest.raises(ValueError, match="at least one valid"):
        sample_context_and_targets(Episodes(torch.zeros(2, 5, 2), torch.zeros(2, 5), valid), 3, 3)


def test_nll_falls_on_toy_fit():
    model = CNMPModel(encoder_layers=(64, 64), decoder_layers=(64, 64)).fit(
        toy_demos(), steps=300, batch_size=16, progress=False
    )
    first = np.mean([h["nll"] for h in model.history[:2]])
    last = np.mean([h["nll"] for h in model.history[-2:]])
    assert last < first - 1.0, (first, last)
    # The mode is selected by a via-point: conditioned at the top, the middle goes up, and vice versa.
    up, _ = model.predict([0.5], [Condition(0.25, (0.25, 0.28))])
    down, _ = model.predict([0.5], [Condition(0.25, (0.25, -0.28))])
    assert up[0, 1] > 0.2 and down[0, 1] < -0.2


def test_task_parameters_are_used():
    """Demos whose amplitude is the task parameter: predictions follow γ without any other condition."""
    tau = np.linspace(0, 1, 40)
    gam = np.linspace(-1, 1, 9)[:, None]
    demos = np.stack([np.stack([tau, g[0] * np.sin(np.pi * tau)], 1) for g in gam])
    model = CNMPModel(encoder_layers=(64, 64), decoder_layers=(64, 64), optimizer_lr=3e-3).fit(
        demos, task_params=gam, steps=1200, batch_size=16, progress=False
    )
    hi, _ = model.predict([0.5], [Condition(0.0, (0.0, 0.0))], task_params=[0.75])
    lo, _ = model.predict([0.5], [Condition(0.0, (0.0, 0.0))], task_params=[-0.75])
    assert hi[0, 1] > 0.4 and lo[0, 1] < -0.4
    with pytest.raises(ValueError, match="task parameters"):
        model.predict([0.5], [Condition(0.0, (0.0, 0.0))])


@pytest.fixture(scope="module")
def fitted():
    return CNMPModel(encoder_layers=(32, 32), decoder_layers=(32, 32)).fit(
        toy_demos(), steps=30, batch_size=8, progress=False
    )


@pytest.mark.parametrize(
    "conditions, phases, match",
    [
        ([Condition(0.5, (0.5,))], [0.5], "SM has 2 dims"),
        ([Condition(1.5, (0.5, 0.1))], [0.5], "outside"),
        ([Condition(-0.1, (0.5, 0.1))], [0.5], "outside"),
        ([Condition(0.5, (float("nan"), 0.1))], [0.5], "NaN"),
        ([Condition(0.5, (0.5, 0.1), dims=(3,))], [0.5], "dims"),
        ([], [0.5], "empty context"),
        ([Condition(0.5, (0.5, 0.1))], [1.2], "phases"),
        ([Condition(0.5, (0.5, 0.1))], [np.nan], "phases"),
    ],
)
def test_bad_prediction_inputs(fitted, conditions, phases, match):
    with pytest.raises(ValueError, match=match):
        fitted.predict(phases, conditions)


def test_nan_in_unconstrained_dim_is_fine(fitted):
    mean, _ = fitted.predict([0.5], [Condition(0.5, (float("nan"), 0.1), dims=(1,))])
    assert np.isfinite(mean).all()


@pytest.mark.parametrize(
    "demos, match",
    [
        (np.zeros((3, 10)), r"\[T, D\]"),
        ([np.zeros((10, 2)), np.zeros((10, 3))], "SM dimension"),
        ([np.zeros((1, 2))], "at least 2"),
        (np.full((2, 10, 2), np.nan), "NaN"),
        ([], "no demonstrations"),
    ],
)
def test_bad_demos(demos, match):
    with pytest.raises(ValueError, match=match):
        CNMPModel().fit(demos, steps=1, progress=False)


def test_bad_task_params_shape():
    with pytest.raises(ValueError, match="task_params"):
        CNMPModel().fit(toy_demos(n=4), task_params=np.zeros((3, 1)), steps=1, progress=False)


def test_demos_of_different_lengths():
    values, valid, phase = pad_demos([np.zeros((5, 2)), np.ones((9, 2))])
    assert values.shape == (2, 9, 2) and valid.sum() == 14
    assert phase[0, 4] == 1.0 and phase[1, 8] == 1.0 and phase[0, 5] == 0.0
    CNMPModel(encoder_layers=(16,), decoder_layers=(16,)).fit(
        [np.zeros((5, 2)), np.ones((9, 2))], steps=3, batch_size=4, progress=False
    )


def test_save_load_bit_identical(fitted, tmp_path):
    fitted.save(tmp_path / "ckpt")
    loaded = CNMPModel.load(tmp_path / "ckpt")
    conds = [Condition(0.3, (0.3, 0.2)), Condition(1.0, (1.0, 0.0), dims=(1,))]
    q = np.linspace(0, 1, 33)
    a, b = fitted.predict(q, conds), loaded.predict(q, conds)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_checkpoint_of_another_config_is_rejected(fitted, tmp_path):
    fitted.save(tmp_path / "small")
    # Same file, other layer sizes: the weights cannot fit.
    import json

    cfg_path = tmp_path / "small" / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["encoder_layers"] = [64, 64]
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="do not fit this CNMP configuration"):
        CNMPModel.load(tmp_path / "small")
    cfg["type"] = "act"
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="'act' policy"):
        CNMPModel.load(tmp_path / "small")


def test_not_a_checkpoint(tmp_path):
    (tmp_path / "pretrained_model").mkdir()
    (tmp_path / "pretrained_model" / "config.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="did you mean"):
        CNMPModel.load(tmp_path)


@pytest.mark.parametrize(
    "field, value",
    [("min_std", 0.0), ("n_max_context", 0), ("partial_obs_prob", 1.5), ("demo_duration_s", 0.0),
     ("control_fps", -1.0), ("sensed_obs_prob", 2.0), ("draws_per_sample", 0), ("phase_frequencies", -1)],
)
def test_bad_config_values(field, value):
    section = {"control_fps": "execution", "n_max_context": "sampling", "partial_obs_prob": "sampling",
               "sensed_obs_prob": "sampling", "draws_per_sample": "sampling"}.get(field)
    with pytest.raises(ValueError, match=field):
        CNMPConfig(**({section: {field: value}} if section else {field: value}))


def test_context_in_targets_puts_observations_among_queries():
    values = torch.randn(4, 20, 2)
    valid = torch.ones(4, 20, dtype=torch.bool)
    ep = Episodes(values, torch.rand(4, 20), valid)
    ctx, tgt = sample_context_and_targets(ep, 3, 5, generator=torch.Generator().manual_seed(1), context_in_targets=True)
    n = ctx.phase.shape[1]
    assert tgt.phase.shape[1] == n + 5
    torch.testing.assert_close(tgt.values[:, :n], ctx.values)
    assert torch.equal(tgt.valid[:, :n], ctx.valid)


def test_phase_fourier_features():
    net = CNMP(sm_dim=2, encoder_layers=(16,), decoder_layers=(16,), phase_frequencies=3)
    f = net.phase_features(torch.tensor([[0.0, 0.5]]))
    assert f.shape == (1, 2, 7)
    torch.testing.assert_close(f[0, 1, 1:4], torch.sin(torch.pi * torch.tensor([0.5, 1.0, 1.5])))
    mean, std = net(random_context(b=1, n=2), torch.rand(1, 3))
    assert mean.shape == (1, 3, 2)
    assert CNMP(sm_dim=2).phase_features(torch.zeros(1, 2)).shape == (1, 2, 1)  # paper default: raw t


def test_cosine_schedule_decays_over_the_run():
    cfg = CNMPConfig(optimizer_lr=1e-3, scheduler_decay_lr=1e-5)
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1e-3)
    sched = cfg.get_scheduler_preset().build(opt, 100)
    lrs = []
    for _ in range(100):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] < 2e-5 and all(a >= b for a, b in zip(lrs, lrs[1:]))
    assert CNMPConfig(scheduler_decay_lr=None).get_scheduler_preset() is None


def test_fit_callback_sees_progress_and_can_stop():
    seen = []

    def callback(done, model):
        seen.append((done, model.policy.training))
        return done >= 20

    model = CNMPModel(encoder_layers=(16,), decoder_layers=(16,)).fit(
        toy_demos(), steps=100, batch_size=4, progress=False, callback=callback, callback_every=10
    )
    assert seen == [(10, False), (20, False)]  # eval mode inside the callback; stopped at 20
    assert not model.policy.training and model.history[-1]["step"] < 20
    with pytest.raises(ValueError, match="callback_every"):
        CNMPModel().fit(toy_demos(), steps=5, callback_every=0)


def test_optimizer_preset_is_fused_adam_and_switchable():
    params = [torch.nn.Parameter(torch.zeros(3))]
    assert CNMPConfig().get_optimizer_preset().build(params).defaults["fused"] is True
    off = CNMPConfig(optimizer_fused=False).get_optimizer_preset()
    assert off.type == "cnmp_adam" and not off.build(params).defaults["fused"]


@pytest.mark.parametrize("task_dim,freqs", [(0, 0), (2, 0), (1, 3)])
def test_numpy_executor_equals_the_torch_model(task_dim, freqs):
    torch.manual_seed(2)
    m = CNMP(sm_dim=2, task_dim=task_dim, encoder_layers=(16, 8), decoder_layers=(16, 16), phase_frequencies=freqs)
    ctx = random_context(b=3, n=5, g=task_dim)
    ctx.valid[1, 3:] = False  # padded entries must not count
    q = torch.rand(3, 7)
    with torch.no_grad():
        mean, std = m(ctx, q)
    n_mean, n_std = NumpyCNMP(m)(ctx, q)
    torch.testing.assert_close(n_mean, mean, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(n_std, std, atol=1e-5, rtol=1e-5)


# ---- the mixture decoder (CNEP, n_experts K > 1) ----------------------------------------------------------


def test_one_expert_is_todays_model_bit_for_bit():
    """K = 1 (the default) keeps today's parameter names, initialization and outputs: the figures below were
    computed by the code before the mixture existed (commit 53efd9f), same seed, same inputs."""
    torch.manual_seed(0)
    m = CNMP(sm_dim=2, task_dim=1, encoder_layers=(8, 8), decoder_layers=(8, 8))
    assert n_experts(m) == 1 and not isinstance(m, MixtureCNMP)
    assert sorted(m.state_dict()) == sorted(f"{n}.{i}.{p}" for n in ("encoder", "decoder") for i in (0, 2, 4)[: 3 if n == "decoder" else 2]
                                            for p in ("weight", "bias"))
    gen = torch.Generator().manual_seed(3)
    ctx = Context(torch.rand(2, 3, generator=gen), torch.randn(2, 3, 2, generator=gen), torch.ones(2, 3, 2),
                  torch.ones(2, 3, dtype=torch.bool), torch.randn(2, 1, generator=gen))
    q = torch.rand(2, 2, generator=gen)
    targets = Targets(q, torch.randn(2, 2, 2, generator=gen), torch.ones(2, 2, dtype=torch.bool))
    mean, std = m(ctx, q)
    before_mean = [[[0.048614129424095154, 0.027116576209664345], [0.04845230281352997, 0.028841551393270493]],
                   [[0.04762108623981476, 0.028265612199902534], [0.04754894599318504, 0.029505781829357147]]]
    before_std = [[[0.59080570936203, 0.7658947110176086], [0.5897484421730042, 0.7639021873474121]],
                  [[0.5895143747329712, 0.7606388330459595], [0.5910351872444153, 0.7653103470802307]]]
    torch.testing.assert_close(mean, torch.tensor(before_mean), rtol=0, atol=1e-7)
    torch.testing.assert_close(std, torch.tensor(before_std), rtol=0, atol=1e-7)
    loss, info = m.training_loss(ctx, targets)
    assert loss.item() == pytest.approx(2.223935604095459, abs=1e-6) and set(info) == {"nll", "mae", "std"}
    # the mixture view of a single decoder: one expert of probability 1, the same (μ, σ)
    means, stds, probs = mixture_of(m, ctx, q)
    assert torch.equal(means[:, 0], mean) and torch.equal(stds[:, 0], std) and torch.equal(probs, torch.ones(2, 1))


@pytest.fixture(scope="module")
def mixture_net():
    torch.manual_seed(0)
    return MixtureCNMP(sm_dim=2, task_dim=1, encoder_layers=(32, 32), decoder_layers=(32, 32), n_experts=3).eval()


def test_mixture_shapes_gate_sums_to_one_and_decode_is_the_most_probable_expert(mixture_net):
    ctx = random_context(b=5, g=1)
    q = torch.rand(5, 7)
    means, stds, probs = mixture_net.mixture(ctx, q)
    assert means.shape == stds.shape == (5, 3, 7, 2) and probs.shape == (5, 3)
    torch.testing.assert_close(probs.sum(-1), torch.ones(5))
    assert bool((probs > 0).all()) and bool((stds >= mixture_net.min_std).all())
    mean, std = mixture_net(ctx, q)
    k = probs.argmax(-1)
    torch.testing.assert_close(mean, means[torch.arange(5), k])
    torch.testing.assert_close(std, stds[torch.arange(5), k])
    # each expert is its own network: the experts' predictions differ
    assert float((means[:, 0] - means[:, 1]).abs().max().detach()) > 1e-3


def test_mixture_experts_equal_the_plain_networks(mixture_net):
    """Expert k's stacked, first-layer-split computation is Q_k([t_q, γ, r]) with its own weights."""
    m = mixture_net
    ctx = random_context(b=2, g=1)
    q = torch.rand(2, 4)
    r = m.condition(ctx)
    means, stds = m.decode_experts(r, q, ctx.task_params)
    x = torch.cat([q[..., None], ctx.task_params[:, None].expand(-1, 4, -1), r[:, None].expand(-1, 4, -1)], -1)
    for k in range(3):
        h = x
        for i, (w, b) in enumerate(zip(m.decoders.weights, m.decoders.biases, strict=True)):
            h = torch.nn.functional.linear(h if i == 0 else torch.relu(h), w[k], b[k])
        torch.testing.assert_close(means[:, k], h[..., :2])
        torch.testing.assert_close(stds[:, k], m.min_std + torch.nn.functional.softplus(h[..., 2:]))
    torch.testing.assert_close(m.gate_probs(r), torch.softmax(r @ m.gate.weight.T + m.gate.bias, -1))


@pytest.mark.parametrize("shared", [0, 1])
def test_mixture_permutation_and_padding_invariance_for_every_expert(mixture_net, shared):
    """Separate experts and a shared trunk (shared_decoder_layers, the config's default for K > 1)."""
    if shared:
        torch.manual_seed(0)
        mixture_net = MixtureCNMP(sm_dim=2, task_dim=1, encoder_layers=(32, 32), decoder_layers=(32, 32), n_experts=3,
                                  shared_decoder_layers=shared).eval()
    ctx = random_context(b=3, n=5, g=1)
    q = torch.rand(3, 4)
    perm = torch.tensor([4, 2, 0, 3, 1])
    shuffled = Context(ctx.phase[:, perm], ctx.values[:, perm], ctx.mask[:, perm], ctx.valid[:, perm], ctx.task_params)
    pad = 3
    padded = Context(
        torch.cat([ctx.phase, torch.rand(3, pad)], 1), torch.cat([ctx.values, 100 * torch.randn(3, pad, 2)], 1),
        torch.cat([ctx.mask, torch.ones(3, pad, 2)], 1),
        torch.cat([ctx.valid, torch.zeros(3, pad, dtype=torch.bool)], 1), ctx.task_params)
    ref = mixture_net.mixture(ctx, q)
    for other in (shuffled, padded):
        for a, b in zip(ref, mixture_net.mixture(other, q), strict=True):
            torch.testing.assert_close(a, b)  # every expert's μ and σ, and the gate


def test_mixture_loss_assigned(mixture_net):
    """assigned: the unconditional mixture's likelihood (experts and gate on r = 0) plus each context's experts
    and gate trained on the episode's expert ρ from it (no gradient through ρ); batch entropy on the
    unconditional per-query posterior. Without the empty-context terms it is a clear error."""
    ctx = random_context(b=4, g=1)
    targets = Targets(torch.rand(4, 6), torch.randn(4, 6, 2), torch.rand(4, 6) < 0.8)
    targets.valid[:, 0] = True
    loss, info = mixture_net.training_loss(ctx, targets)
    means, stds, probs = mixture_net.mixture(ctx, targets.phase)
    r0 = torch.zeros(4, 32)
    means0, stds0 = mixture_net.decode_experts(r0, targets.phase, ctx.task_params)
    probs0 = mixture_net.gate_probs(r0)
    n = targets.valid.sum(-1).float()
    nll_bk, nll0_bk = (MixtureCNMP.nll_per_expert(m, s, targets) for m, s in ((means, stds), (means0, stds0)))
    log_joint = probs0.log() - nll0_bk * n[:, None]
    rho = torch.softmax(log_joint, -1)
    want_nll = -(torch.logsumexp(log_joint, -1) / n).mean() + (rho * (nll_bk - probs.log())).sum(-1).mean()
    h = lambda p: -(p * p.log()).sum(-1)  # noqa: E731
    tempered = torch.softmax(probs0.log() - nll0_bk, -1)
    want = (want_nll + mixture_net.gate_entropy_coef * h(probs).mean() / np.log(3)
            - mixture_net.batch_entropy_coef * h(tempered.mean(0)) / np.log(3))
    torch.testing.assert_close(loss, want)
    assert info["nll"] == pytest.approx(want_nll.item(), rel=1e-5)
    assert set(info) >= {"prior_nll", "assigned_nll", "min_expert_share"}
    # unconditional_nll_coef c weighs the unconditional mixture's term only: L(c) - L(1) = (c - 1) NLL⁰_mix
    mixture_net.unconditional_nll_coef = 0.25
    try:
        loss_c, info_c = mixture_net.training_loss(ctx, targets)
    finally:
        mixture_net.unconditional_nll_coef = 1.0
    prior_term = -(torch.logsumexp(log_joint, -1) / n).mean()
    torch.testing.assert_close(loss_c, want - 0.75 * prior_term)
    assert info_c["prior_nll"] == pytest.approx(prior_term.item(), rel=1e-5)


@pytest.mark.parametrize("p", [1, 2])
def test_assignment_draws_decides_one_expert_per_episode_from_its_first_draws(mixture_net, p):
    """assignment_draws = p: the empty-context pass runs on each episode's first p draws only; the episode's
    ρ (from all their queries) is shared by every draw of it. 6 rows = 2 episodes x 3 draws."""
    ctx = random_context(b=6, g=1)
    targets = Targets(torch.rand(6, 5), torch.randn(6, 5, 2), torch.rand(6, 5) < 0.8)
    targets.valid[:, 0] = True
    mixture_net.assignment_draws = p
    try:
        loss, info = mixture_net.training_loss(ctx, targets, draws=3)
        with pytest.raises(ValueError, match="whole number of episodes"):
            mixture_net.training_loss(ctx, targets, draws=4)
    finally:
        mixture_net.assignment_draws = 0
    means, stds, probs = mixture_net.mixture(ctx, targets.phase)
    r0 = torch.zeros(6, 32)
    means0, stds0 = mixture_net.decode_experts(r0, targets.phase, ctx.task_params)
    probs0 = mixture_net.gate_probs(r0)[:2]
    n = targets.valid.sum(-1).float()
    nll_bk, nll0_bk = (MixtureCNMP.nll_per_expert(m, s, targets) for m, s in ((means, stds), (means0, stds0)))
    first = [e * 3 + j for e in range(2) for j in range(p)]  # the rows the empty-context pass sees
    sum0 = (nll0_bk * n[:, None])[first].reshape(2, p, 3).sum(1)  # [E, K]: -log Π_q N⁰ over those queries
    n0 = n[first].reshape(2, p).sum(1)
    log_joint = probs0.log() - sum0
    rho = torch.softmax(log_joint, -1).repeat_interleave(3, 0)
    want_nll = -(torch.logsumexp(log_joint, -1) / n0).mean() + (rho * (nll_bk - probs.log())).sum(-1).mean()
    h = lambda q: -(q * q.log()).sum(-1)  # noqa: E731
    tempered = torch.softmax(probs0.log() - sum0 / n0[:, None], -1)
    want = (want_nll + mixture_net.gate_entropy_coef * h(probs).mean() / np.log(3)
            - mixture_net.batch_entropy_coef * h(tempered.mean(0)) / np.log(3))
    torch.testing.assert_close(loss, want)
    assert info["nll"] == pytest.approx(want_nll.item(), rel=1e-5)


def test_unconditional_nll_coef_must_be_positive_and_only_with_a_mixture():
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="unconditional_nll_coef must be a finite number > 0"):
            MixtureCNMP(sm_dim=2, n_experts=2, unconditional_nll_coef=bad)
        with pytest.raises(ValueError, match="unconditional_nll_coef must be a finite number > 0"):
            CNMPConfig(n_experts=2, mixture={"unconditional_nll_coef": bad})
    with pytest.raises(ValueError, match="unconditional_nll_coef=0.5 applies to a mixture, but n_experts is 1"):
        CNMPConfig(mixture={"unconditional_nll_coef": 0.5})
    assert CNMPConfig(n_experts=2, mixture={"unconditional_nll_coef": 0.5}).mixture.unconditional_nll_coef == 0.5


def test_assignment_draws_must_be_a_count():
    with pytest.raises(ValueError, match="assignment_draws"):
        MixtureCNMP(sm_dim=2, n_experts=2, assignment_draws=-1)
    for bad in (1.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="assignment_draws must be an integer"):
            CNMPConfig(n_experts=2, mixture={"assignment_draws": bad})
        with pytest.raises(ValueError, match="assignment_draws must be an integer"):
            MixtureCNMP(sm_dim=2, n_experts=2, assignment_draws=bad)
    with pytest.raises(ValueError, match="assignment_draws=2 applies to a mixture"):  # it would do nothing
        CNMPConfig(mixture={"assignment_draws": 2})
    assert CNMPConfig(n_experts=2, mixture={"assignment_draws": 2}).mixture.assignment_draws == 2


def test_revive_starving_gives_an_idle_expert_the_episode_it_fits_least_badly():
    net = MixtureCNMP(sm_dim=2, n_experts=3)
    log_joint = torch.tensor([[0.0, -50.0, -9.0], [-40.0, 0.0, -3.0], [0.0, -1.0, -30.0], [-2.0, 0.0, -60.0]])
    net.eval()
    assert torch.equal(net.revive_starving(log_joint), log_joint)  # evaluation: untouched, nothing tracked
    torch.testing.assert_close(net.expert_share, torch.full((3,), 1 / 3))
    net.train()
    assert torch.equal(net.revive_starving(log_joint), log_joint)  # every expert's running share is >= 1/(4K)
    torch.testing.assert_close(net.expert_share, 0.99 * torch.full((3,), 1 / 3) + 0.01 * torch.tensor([0.5, 0.5, 0]))
    net.expert_share.copy_(torch.tensor([0.5, 0.5, 0.05]))  # expert 2 starves: it gets episode 1 (gap 3)
    out = net.revive_starving(log_joint)
    assert torch.equal(torch.softmax(out, -1)[1], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(out[[0, 2, 3]], log_joint[[0, 2, 3]])
    assert "expert_share" not in net.state_dict()  # training state only: checkpoints are unchanged


@pytest.mark.parametrize("k", [0, -2, 1.5, float("nan"), float("inf"), 1])
def test_bad_number_of_experts_is_a_clear_error(k):
    if k != 1:  # K = 1 is the plain CNMP's config, not a mixture's
        with pytest.raises(ValueError, match="n_experts"):
            CNMPConfig(n_experts=k)
    with pytest.raises(ValueError, match="n_experts"):
        MixtureCNMP(sm_dim=2, n_experts=k)


@pytest.mark.parametrize("field, value", [("gate_entropy_coef", -0.1), ("batch_entropy_coef", -1.0),
                                          ("expert_selection", "random"), ("mode_switch_margin", 1.0)])
def test_bad_mixture_settings(field, value):
    with pytest.raises(ValueError, match=field):
        CNMPConfig(mixture={field: value})


def test_numpy_copy_refuses_a_mixture(mixture_net):
    with pytest.raises(ValueError, match="experts"):
        NumpyCNMP(mixture_net)


@pytest.fixture(scope="module")
def fitted_mixture():
    """Two experts on the two-mode toy (bump up / bump down, same start and end)."""
    torch.manual_seed(0)
    return CNMPModel(encoder_layers=(32, 32), decoder_layers=(32, 32), n_experts=2).fit(
        toy_demos(n=16), steps=800, batch_size=16, progress=False)


def test_mixture_separates_the_two_modes(fitted_mixture):
    """Given a point of one mode the gate commits to one expert, and that expert draws that mode; the two
    modes go to different experts. The single-decoder CNMP's answer to the shared start alone is the
    average of the modes; the mixture's experts are the modes themselves."""
    q = np.linspace(0, 1, 50)
    up = fitted_mixture.predict_mixture(q, [Condition(0.5, (0.5, 0.4))])
    down = fitted_mixture.predict_mixture(q, [Condition(0.5, (0.5, -0.4))])
    for (means, _, probs), sign in ((up, 1), (down, -1)):
        k = int(probs.argmax())
        assert probs[k] > 0.9
        assert sign * means[k, 25, 1] > 0.25  # the chosen expert's mid-point is on that mode's side
        mean, _ = fitted_mixture.predict(q, [Condition(0.5, (0.5, 0.4 * sign))])
        np.testing.assert_array_equal(mean, means[k])  # predict = the most probable expert
    assert int(up[2].argmax()) != int(down[2].argmax())
    means, _, probs = fitted_mixture.predict_mixture(q, [Condition(0.0, (0.0, 0.0))])
    assert sorted(np.sign(means[:, 25, 1]).tolist()) == [-1.0, 1.0]  # shared start: both modes are experts
    np.testing.assert_allclose(probs.sum(), 1.0, rtol=1e-6)


def test_mixture_gives_each_mode_its_expert_and_shares_at_the_shared_start(fitted_mixture):
    """The two-mode toy: a mid point commits the gate (> 0.9) to the expert of its mode, the two modes to
    different experts; the shared start, which does not name a mode, gets both."""
    model = fitted_mixture
    q = np.linspace(0, 1, 50)
    chosen = []
    for sign in (1, -1):
        means, _, probs = model.predict_mixture(q, [Condition(0.5, (0.5, 0.4 * sign))])
        k = int(probs.argmax())
        assert probs[k] > 0.9 and sign * means[k, 25, 1] > 0.25
        chosen.append(k)
    assert chosen[0] != chosen[1]
    _, _, probs = model.predict_mixture(q, [Condition(0.0, (0.0, 0.0))])
    assert probs.min() > 0.25, probs


def test_predict_a_chosen_expert_and_bad_expert(fitted_mixture):
    q = np.linspace(0, 1, 9)
    conds = [Condition(0.0, (0.0, 0.0))]
    means, stds, _ = fitted_mixture.predict_mixture(q, conds)
    for k in range(2):
        mean, std = fitted_mixture.predict(q, conds, expert=k)
        np.testing.assert_array_equal(mean, means[k])
        np.testing.assert_array_equal(std, stds[k])
    with pytest.raises(ValueError, match="expert"):
        fitted_mixture.predict(q, conds, expert=2)


def test_mixture_save_load_bit_identical(fitted_mixture, tmp_path):
    fitted_mixture.save(tmp_path / "mix")
    loaded = CNMPModel.load(tmp_path / "mix")
    assert loaded.config.n_experts == 2
    conds = [Condition(0.3, (0.3, 0.2))]
    q = np.linspace(0, 1, 33)
    for a, b in zip(fitted_mixture.predict_mixture(q, conds), loaded.predict_mixture(q, conds), strict=True):
        assert np.array_equal(a, b)


def test_api_fit_with_a_seed_is_reproducible_from_initialization_on():
    from lerobot_cnmp.api import CNMPModel

    demos = np.sin(np.linspace(0, 3, 20))[None, :, None].repeat(3, 0) + np.arange(3)[:, None, None]
    fits = [CNMPModel(encoder_layers=(16, 16), decoder_layers=(16, 16)).fit(demos, steps=5, batch_size=2, seed=3,
                                                                            progress=False) for _ in range(2)]
    a, b = (torch.cat([p.detach().reshape(-1) for p in f.policy.parameters()]) for f in fits)
    assert torch.equal(a, b)


def test_shared_decoder_layers():
    """A trunk shared by the experts gives each expert trunk -> own layers; bad sizes are a clear error."""
    import torch.nn.functional as F

    r, q = torch.randn(4, 128), torch.rand(4, 7)
    for shared in (2, 3):  # the experts' own last hidden layer and output; their output layer only
        net = MixtureCNMP(sm_dim=3, n_experts=3, shared_decoder_layers=shared)
        mean, std = net.decode_experts(r, q)
        for k in range(3):
            x = F.relu(net.trunk(torch.cat([q[..., None], r[:, None].expand(-1, 7, -1)], -1)))
            for i in range(len(net.decoders.weights)):
                x = F.linear(F.relu(x) if i else x, net.decoders.weights[i][k], net.decoders.biases[i][k])
            assert torch.allclose(x[..., :3], mean[:, k], atol=1e-5)
            assert torch.allclose(net.min_std + F.softplus(x[..., 3:]), std[:, k], atol=1e-5)
    with pytest.raises(ValueError, match="shared_decoder_layers"):
        MixtureCNMP(sm_dim=2, n_experts=2, shared_decoder_layers=4)
    with pytest.raises(ValueError, match="n_experts is 1"):
        CNMPConfig(mixture={"shared_decoder_layers": 1})
    # the default: a mixture shares all hidden layers, K = 1 shares nothing; 0 keeps CNEP's K networks
    assert CNMPConfig(n_experts=4).mixture.shared_decoder_layers == 3 and CNMPConfig().mixture.shared_decoder_layers == 0
    assert CNMPConfig(n_experts=4, decoder_layers=(64,)).mixture.shared_decoder_layers == 1
    assert CNMPConfig(n_experts=4, mixture={"shared_decoder_layers": 0}).mixture.shared_decoder_layers == 0


def test_mixture_parameter_names_are_the_checkpoints():
    """The mixture's parameters keep their names in checkpoints: trunk.*, decoders.weights/biases.*, gate.*."""
    net = MixtureCNMP(sm_dim=2, encoder_layers=(8, 8), decoder_layers=(8, 8, 8), n_experts=2, shared_decoder_layers=2)
    names = set(net.state_dict())
    assert names == ({f"encoder.{i}.{p}" for i in (0, 2) for p in ("weight", "bias")}
                     | {f"trunk.{i}.{p}" for i in (0, 2) for p in ("weight", "bias")}
                     | {f"decoders.{p}.{i}" for p in ("weights", "biases") for i in (0, 1)}
                     | {"gate.weight", "gate.bias"})


# ---- the decoder term linear in γ (linear_task_term) ---------------------------------------------------------


def test_linear_task_term_starts_at_zero_and_keeps_the_mlp_initialization():
    torch.manual_seed(4)
    plain = CNMP(sm_dim=2, task_dim=3, encoder_layers=(16,), decoder_layers=(16,), phase_frequencies=2)
    torch.manual_seed(4)
    lin = CNMP(sm_dim=2, task_dim=3, encoder_layers=(16,), decoder_layers=(16,), phase_frequencies=2,
               linear_task_term=True)
    assert set(lin.state_dict()) - set(plain.state_dict()) == {"task_gain"}
    assert lin.task_gain.shape == (2, (1 + 5) * 3) and not lin.task_gain.any()
    ctx, q = random_context(g=3), torch.rand(3, 4)
    with torch.no_grad():
        torch.testing.assert_close(lin(ctx, q), plain(ctx, q), atol=0, rtol=0)
        lin.task_gain.normal_()
        shifted = lin(ctx, q)[0] - plain(ctx, q)[0]
    # A(t)·γ by hand: φ = [1, t, sin kπt, cos kπt], A(t) = Σ_k φ_k A_k
    phi = torch.cat([torch.ones(3, 4, 1), lin.phase_features(q)], -1)
    a = lin.task_gain.reshape(2, 6, 3)
    want = torch.einsum("bmk,dkg,bg->bmd", phi, a, ctx.task_params)
    torch.testing.assert_close(shifted, want, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("freqs", [0, 3])
def test_numpy_executor_equals_the_torch_model_with_the_linear_task_term(freqs):
    torch.manual_seed(5)
    m = CNMP(sm_dim=2, task_dim=2, encoder_layers=(16, 8), decoder_layers=(16, 16), phase_frequencies=freqs,
             linear_task_term=True)
    with torch.no_grad():
        m.task_gain.normal_()
    ctx, q = random_context(b=3, n=5, g=2), torch.rand(3, 7)
    with torch.no_grad():
        mean, std = m(ctx, q)
    n_mean, n_std = NumpyCNMP(m)(ctx, q)
    torch.testing.assert_close(n_mean, mean, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(n_std, std, atol=1e-5, rtol=1e-5)


def test_linear_task_term_needs_gamma():
    with pytest.raises(ValueError, match="needs task parameters"):
        CNMP(sm_dim=2, task_dim=0, linear_task_term=True)


# --- the image encoder's spatial-softmax head and random-shift augmentation ------------------------------------


def test_keypoint_encoder_finds_where_a_bright_spot_is():
    from lerobot_cnmp.model.cnmp import ConvEncoder

    enc = ConvEncoder((3, 32, 32), channels=(1,), embed_dim=2, keypoints=True)  # one conv, not pooled: a 32 x 32 map
    with torch.no_grad():
        enc.conv[0].weight.zero_()
        enc.conv[0].weight[0, 0, 1, 1] = 60.0  # the channel is the red pixel, sharp in the softmax
        enc.conv[0].bias.zero_()
        enc.project.weight.copy_(torch.eye(2))
        enc.project.bias.zero_()
    images = torch.zeros(2, 3, 32, 32)
    images[0, 0, 4, 28] = 1.0  # top right
    images[1, 0, 30, 2] = 1.0  # bottom left
    xy = enc(images)
    grid = torch.linspace(-1, 1, 32)
    torch.testing.assert_close(xy, torch.stack([grid[[28, 4]], grid[[2, 30]]]), atol=1e-3, rtol=0)
    flat = ConvEncoder((3, 32, 32), channels=(4, 4), embed_dim=5)  # the paper's head: pooled, flattened
    assert flat(images).shape == (2, 5) and isinstance(flat.conv[-1], torch.nn.MaxPool2d)


def test_random_shift_crops_the_padded_image_back_to_size():
    from lerobot_cnmp.model.cnmp import random_shift

    images = torch.arange(2 * 3 * 8 * 8, dtype=torch.float32).reshape(2, 3, 8, 8)
    assert random_shift(images, 0) is images
    shifted = random_shift(images, 2, torch.Generator().manual_seed(0))
    assert shifted.shape == images.shape
    padded = torch.nn.functional.pad(images, (2, 2, 2, 2), mode="replicate")
    for i in range(2):  # each is the padded image's 8 x 8 window at some offset
        windows = [padded[i, :, y:y + 8, x:x + 8] for y in range(5) for x in range(5)]
        assert any(torch.equal(shifted[i], w) for w in windows)
    draws = {tuple(random_shift(images, 2, torch.Generator().manual_seed(s))[0, 0, 0, :2].tolist()) for s in range(20)}
    assert len(draws) > 1  # the offset is drawn


def test_image_encoder_shift_must_be_a_count():
    from lerobot_cnmp.policy.image_config import ImageEncoderConfig

    assert ImageEncoderConfig(shift=4).shift == 4
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="image_encoder.shift"):
            ImageEncoderConfig(shift=bad)


def test_centered_encoder_subtracts_the_saved_mean_image(tmp_path):
    from lerobot_cnmp.model.cnmp import ConvEncoder

    torch.manual_seed(0)
    plain = ConvEncoder((3, 16, 16), (4, 4), 3, keypoints=True)
    centered = ConvEncoder((3, 16, 16), (4, 4), 3, keypoints=True, center=True)
    centered.load_state_dict({**plain.state_dict(), "mean_image": torch.rand(3, 16, 16)})
    images = torch.rand(2, 3, 16, 16)
    torch.testing.assert_close(centered(images), plain(images - centered.mean_image))
    assert "mean_image" in centered.state_dict() and "mean_image" not in plain.state_dict()

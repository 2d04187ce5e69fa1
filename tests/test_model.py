"""The CNMP model, its training-step sampler and the in-memory API."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lerobot_cnmp.api import CNMPModel, Condition, pad_demos
from lerobot_cnmp.configuration_cnmp import CNMPConfig
from lerobot_cnmp.modeling_cnmp import CNMP, Context, Episodes, NumpyCNMP, Targets, sample_context_and_targets


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
    with pytest.raises(ValueError, match=field):
        CNMPConfig(**{field: value})


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

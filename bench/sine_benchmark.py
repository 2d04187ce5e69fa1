"""Multimodal sine benchmark, after the published protocol of CNEP (Yildirim & Ugur, arXiv 2402.08424).

    python -m bench.sine_benchmark [--steps 4000] [--seed 0] [--experts 4] [--shared_decoder_layers S]
                                   [--gate_entropy_coef G] [--assignment_draws P]

Data (as in the CNEP code, ``compare_cneps_on_4_sines_abl.py``): 4 modes x 32 demos of 200 steps on
x = linspace(0, 1, 200). Mode i = 0..3: y = (sin((x + 0.2 (i+1)) · (i+1)π/2 + φ) + ε + 1) / 2, with a
per-demo phase φ ~ U(0, 0.05π) and per-step noise ε = max(N(0, 0.01²), 0).

Tests (``comparison_all_numeric_random.ipynb``): 50 points (x0, y0), each drawn at a random step below 150
where two mode means are within 0.1 of each other, with y0 uniform between them; each is used with the end
point of each of the 4 mode means (200 tests of 2 conditions). Modes 0/2 and 1/3 end at nearly the same
value, so a test does not name one true mode: the protocol scores a prediction against the *nearest*
demonstration of any mode, error = min over demos of mean_t |prediction(t) - demo(t)|, averaged over tests.

Published figures on this protocol: ProMP 0.181, GMM-GMR 0.332, CNMP 0.112, CNEP 0.027. Here CNMP is our
``CNMPModel`` with the config's defaults except n_max = m_max = 10 (as there); the mixture is the same
model with ``n_experts`` = 4 decoders and a gate (CNEP's setting; scored, as their code does, on the mean
of the most probable expert), trained with the same steps, batch and seed; ProMP is
``movement_primitives``' with 10 RBFs (as there), scored on its conditioned mean (what it predicts) and, as
the CNEP code did, on one sample of it. Also draws ``--plot`` (CNMP vs ProMP) and ``--mixture_plot`` (each
expert's prediction, opacity and width by its gate probability, beside the demos); the figures in docs/ are
``--plot docs/sine_cnmp_vs_promp.png --mixture_plot docs/sine_mixture.png``.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from bench.common import add_mixture_arguments, mixture_report, mixture_settings

REPO = Path(__file__).resolve().parents[1]
STEPS = 200
N_MODES, DEMOS_PER_MODE, N_TESTS = 4, 32, 50
PUBLISHED = {"promp": 0.181, "gmm_gmr": 0.332, "cnmp": 0.112, "cnep": 0.027}


def make_sines(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(demos [128, 200], mode of each demo [128], mode means [4, 200])."""
    x = np.linspace(0.0, 1.0, STEPS)
    demos, modes = [], []
    for i in range(N_MODES):
        phase = rng.random(DEMOS_PER_MODE) * 0.05 * np.pi
        noise = np.maximum(rng.normal(0.0, 0.01, (DEMOS_PER_MODE, STEPS)), 0.0)
        demos.append((np.sin((x + 0.2 * (i + 1)) * (i + 1) / 2 * np.pi + phase[:, None]) + noise + 1) / 2)
        modes += [i] * DEMOS_PER_MODE
    demos = np.concatenate(demos)
    modes = np.asarray(modes)
    means = np.stack([demos[modes == i].mean(0) for i in range(N_MODES)])
    return demos, modes, means


def draw_tests(means: np.ndarray, rng: np.random.Generator) -> list[tuple[int, float]]:
    """``N_TESTS`` (step, y0): a step < 150 where two mode means are within 0.1, y0 uniform between them."""
    tests = []
    while len(tests) < N_TESTS:
        k = int(rng.integers(0, 150))
        a, b = rng.choice(N_MODES, 2, replace=False)
        if abs(means[a, k] - means[b, k]) < 0.1:
            lo, hi = sorted((means[a, k], means[b, k]))
            tests.append((k, float(rng.uniform(lo, hi))))
    return tests


def condition_sets(tests, means):
    from lerobot_cnmp.execution.conditions import Condition

    x = np.linspace(0.0, 1.0, STEPS)
    return [[Condition(float(x[k]), (y0,)), Condition(1.0, (float(means[mode, -1]),))]
            for mode in range(N_MODES) for k, y0 in tests]


def nearest_demo_error(trajectory: np.ndarray, demos: np.ndarray) -> float:
    """min over demos of the mean absolute error along the trajectory (the protocol's score)."""
    return float(np.abs(trajectory[None, :] - demos).mean(axis=1).min())


def score(trajectories, demos) -> tuple[float, float]:
    errors = np.array([nearest_demo_error(t, demos) for t in trajectories])
    return float(errors.mean()), float(errors.std())


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=4000, help="CNMP training steps (batch 32)")
    p.add_argument("--batch_size", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--experts", type=int, default=4, help="decoders of the mixture CNMP (CNEP: 4); 0 skips it")
    add_mixture_arguments(p)
    p.add_argument("--plot", default=str(REPO / "outputs" / "sine_cnmp_vs_promp.png"))
    p.add_argument("--mixture_plot", default=str(REPO / "outputs" / "sine_mixture.png"))
    args = p.parse_args()
    import torch

    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.promp.baselines import ProMPBaseline

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", 2)))  # 2 unless the environment says
    rng = np.random.default_rng(args.seed)
    demos, modes, means = make_sines(rng)
    tests = draw_tests(means, rng)
    sets = condition_sets(tests, means)
    x = np.linspace(0.0, 1.0, STEPS)

    t0 = time.perf_counter()
    cnmp = CNMPModel(sampling={"n_max_context": 10, "m_max_targets": 10}).fit(
        demos[..., None], steps=args.steps, batch_size=args.batch_size, seed=args.seed, progress=False
    )
    fit_s = time.perf_counter() - t0
    mixture, mix_fit_s = None, None
    if args.experts > 0:
        t0 = time.perf_counter()
        settings = mixture_settings(args)
        mixture = CNMPModel(sampling={"n_max_context": 10, "m_max_targets": 10}, n_experts=args.experts,
                           mixture=settings).fit(
            demos[..., None], steps=args.steps, batch_size=args.batch_size, seed=args.seed, progress=False
        )
        mix_fit_s = time.perf_counter() - t0
    promp = ProMPBaseline(n_weights_per_dim=10).fit(demos[..., None])

    cnmp_traj = [cnmp.predict(x, c)[0][:, 0] for c in sets]
    promp_traj = [promp.predict(x, c)[0][:, 0] for c in sets]
    sample_rng = np.random.RandomState(1234)
    promp_samples = [promp.conditioned(c).sample_trajectories(x, 1, sample_rng)[0, :, 0] for c in sets]

    res = {"sine_tests": len(sets), "cnmp_steps": args.steps, "cnmp_batch_size": args.batch_size,
           "cnmp_fit_s": round(fit_s, 1)}
    rows = [("CNMP (ours)", "cnmp", cnmp_traj), ("ProMP mean", "promp", promp_traj),
            ("ProMP 1 sample", "promp_sample", promp_samples)]
    if mixture is not None:
        rows.insert(1, (f"mixture K={args.experts}", "mixture", [mixture.predict(x, c)[0][:, 0] for c in sets]))
        res.update(mixture_experts=args.experts, mixture_fit_s=round(mix_fit_s, 1),
                   mixture_settings=mixture_report(mixture.config))
    print(f"{'method':<16}{'error (mean ± std)':>22}{'published':>11}")
    for label, key, traj in rows:
        mean, std = score(traj, demos)
        res[f"sine_error_{key}"], res[f"sine_error_{key}_std"] = round(mean, 4), round(std, 4)
        pub = PUBLISHED.get({"promp_sample": "promp", "mixture": "cnep"}.get(key, key))
        print(f"{label:<16}{mean:>13.3f} ± {std:<6.3f}{'' if pub is None else f'{pub:>11.3f}'}")
    for key in ("gmm_gmr",) + (("cnep",) if mixture is None else ()):
        print(f"{key.upper().replace('_', '-'):<16}{'(not run here)':>22}{PUBLISHED[key]:>11.3f}")
    res["sine_published"] = PUBLISHED
    res["sine_plot"] = str(plot(x, demos, modes, sets[:: len(tests) // 2][:4], cnmp, promp, args.plot))
    print(f"plot: {res['sine_plot']}")
    if mixture is not None:
        probs = np.stack([mixture.predict_mixture(x, c)[2] for c in sets])
        res["mixture_gate_max_prob_mean"] = round(float(probs.max(axis=1).mean()), 3)
        res["mixture_expert_use"] = np.bincount(probs.argmax(axis=1), minlength=args.experts).tolist()
        print(f"mixture: mean max gate probability {res['mixture_gate_max_prob_mean']}, tests per expert "
              f"{res['mixture_expert_use']}")
        res["sine_mixture_plot"] = str(plot_mixture(x, demos, modes, sets[:: len(tests) // 2][:4], mixture,
                                                    args.mixture_plot))
        print(f"plot: {res['sine_mixture_plot']}")
    print(json.dumps(res))
    return res


def plot(x, demos, modes, sets, cnmp, promp, path) -> Path:
    """A few tests: demos by mode (thin), CNMP and ProMP mean ± 2σ, the two conditions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(sets), figsize=(4 * len(sets), 3.4), sharey=True)
    colors = plt.get_cmap("tab10")
    for ax, conds in zip(np.atleast_1d(axes), sets, strict=False):
        for i in range(N_MODES):
            ax.plot(x, demos[modes == i].T, color=colors(i), lw=0.4, alpha=0.25)
        for name, model, color in (("CNMP", cnmp, "k"), ("ProMP", promp, "tab:red")):
            mean, std = model.predict(x, conds)
            ax.plot(x, mean[:, 0], color=color, lw=1.8, label=name)
            ax.fill_between(x, mean[:, 0] - 2 * std[:, 0], mean[:, 0] + 2 * std[:, 0], color=color, alpha=0.15)
        ax.plot([c.phase for c in conds], [c.values[0] for c in conds], "o", ms=8, mfc="none", mec="k", mew=2)
        ax.set_xlabel("t")
        ax.set_ylim(-0.1, 1.1)
    np.atleast_1d(axes)[0].set_ylabel("y")
    np.atleast_1d(axes)[0].legend(loc="lower left", fontsize=8)
    fig.suptitle("Multimodal sines: demos by mode, predictions (mean ± 2σ) given the circled conditions")
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, path, dpi=110)


def plot_mixture(x, demos, modes, sets, mixture, path) -> Path:
    """A few tests: demos by mode (thin gray), each expert's mean ± 2σ with opacity/width by its gate π."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lerobot_cnmp.plot import plot_experts, save_figure

    fig, axes = plt.subplots(1, len(sets), figsize=(4 * len(sets), 3.4), sharey=True)
    for ax, conds in zip(np.atleast_1d(axes), sets, strict=False):
        ax.plot(x, demos.T, color="0.6", lw=0.4, alpha=0.25)
        plot_experts(ax, x, *mixture.predict_mixture(x, conds))
        ax.plot([c.phase for c in conds], [c.values[0] for c in conds], "o", ms=8, mfc="none", mec="k", mew=2)
        ax.set_xlabel("t")
        ax.set_ylim(-0.1, 1.1)
        ax.legend(loc="lower left", fontsize=7)
    np.atleast_1d(axes)[0].set_ylabel("y")
    fig.suptitle("Mixture CNMP on the sines: each expert's prediction, opacity and width by its gate probability")
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


if __name__ == "__main__":
    main()

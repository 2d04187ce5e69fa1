"""Figures: demonstrations and conditioned predictions (mean ± 2σ), as in the paper's Fig. 4.

    lerobot-cnmp-plot --checkpoint outputs/train/cnmp_obstacle2d/checkpoints/last/pretrained_model \
                      --dataset datasets/cnmp_obstacle2d --out outputs/fig4_cnmp.png

Each panel is one condition set: demos (colored by their avoidance mode), the obstacle, the condition
points (black dots) and the predicted SM trajectory, mean (black) and ± 2σ band (gray).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from lerobot_cnmp.execution.conditions import Condition

Predictor = Callable[[np.ndarray, list[Condition]], tuple[np.ndarray, np.ndarray]]


def plot_conditioned_xy(
    demos: list[np.ndarray],
    panels: dict[str, list[Condition]],
    predictors: dict[str, Predictor],
    out: str | Path,
    demo_colors: list | None = None,
    obstacle: tuple[tuple[float, float], float] | None = None,
    n_phases: int = 200,
) -> Path:
    """One row per predictor, one column per condition set, in the SM's first two dims (x, y)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = len(predictors), len(panels)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    phases = np.linspace(0.0, 1.0, n_phases)
    for r, (pname, predict) in enumerate(predictors.items()):
        for c, (title, conds) in enumerate(panels.items()):
            ax = axes[r, c]
            for i, d in enumerate(demos):
                color = demo_colors[i] if demo_colors is not None else "tab:blue"
                ax.plot(d[:, 0], d[:, 1], color=color, lw=0.8, alpha=0.55)
            if obstacle is not None:
                ax.add_patch(plt.Circle(obstacle[0], obstacle[1], color="0.35", alpha=0.8))
            mean, std = predict(phases, conds)
            ax.fill_between(mean[:, 0], mean[:, 1] - 2 * std[:, 1], mean[:, 1] + 2 * std[:, 1],
                            color="0.5", alpha=0.35, lw=0, label="± 2σ")
            ax.plot(mean[:, 0], mean[:, 1], color="k", lw=2, label=f"{pname} mean")
            for cond in conds:
                x = cond.values[0] if cond.dims is None or 0 in cond.dims else None
                if x is None:  # y-only condition: a horizontal tick at the predicted x
                    x = float(np.interp(cond.phase, phases, mean[:, 0]))
                ax.plot([x], [cond.values[1]], "o", color="k", ms=7, zorder=5)
            ax.set_title(f"{pname}: {title}", fontsize=9)
            ax.set_aspect("equal")
            ax.set_xlim(-0.1, 1.1)
            ax.set_ylim(-0.7, 0.7)
            if c == 0:
                ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return save_figure(fig, out, dpi=120)


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (its folder made if missing), close it and return the path: the tail every
    figure of the package and of ``bench/`` shares."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_experts(ax, x: np.ndarray, means: np.ndarray, stds: np.ndarray, probs: np.ndarray, dim: int = 0,
                 colors=None, min_alpha: float = 0.08) -> None:
    """A mixture CNMP's experts on ``ax``: expert k's mean (and ± 2σ band) of SM dim ``dim`` over ``x``,
    drawn with opacity and line width growing with its gate probability π_k (labelled in the legend).

    ``means``/``stds`` [K, M, D], ``probs`` [K] (``CNMPModel.predict_mixture``). An expert of π_k ≈ 0 stays
    faintly visible (``min_alpha``) so that what the gate rejected can be seen too."""
    import matplotlib.pyplot as plt

    colors = colors or plt.get_cmap("Dark2")
    for k in np.argsort(probs):  # the most probable on top
        p = float(probs[k])
        color = colors(int(k)) if callable(colors) else colors[int(k)]
        alpha = min_alpha + (1 - min_alpha) * p
        m, s = means[k, :, dim], stds[k, :, dim]
        ax.fill_between(x, m - 2 * s, m + 2 * s, color=color, alpha=0.15 * alpha, lw=0)
        ax.plot(x, m, color=color, alpha=alpha, lw=0.8 + 2.4 * p, label=f"expert {k}: π = {p:.2f}")


def mode_colors(demos: list[np.ndarray]) -> list[str]:
    """Blue for demos above the obstacle at mid-motion (mode +1), orange below (mode -1)."""
    return ["tab:blue" if d[len(d) // 2, 1] > 0 else "tab:orange" for d in demos]


def paper_figure(checkpoint: str | Path, dataset: str | Path, out: str | Path) -> Path:
    """The paper's Fig. 4 (CNMP row) for the obstacle task, from a checkpoint and its dataset."""
    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.sims.obstacle2d.model import OBSTACLE_CENTER, OBSTACLE_RADIUS
    from lerobot_cnmp.sims.obstacle2d.task import PAPER_CONDITIONS

    model = CNMPModel.load(checkpoint)
    data = load_demos(dataset)
    return plot_conditioned_xy(
        data["demos"],
        PAPER_CONDITIONS,
        {"CNMP": model.predict},
        out,
        demo_colors=mode_colors(data["demos"]),
        obstacle=(tuple(OBSTACLE_CENTER), OBSTACLE_RADIUS),
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lerobot-cnmp-plot", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="pretrained_model folder of a CNMP checkpoint")
    p.add_argument("--dataset", default="datasets/cnmp_obstacle2d", help="root of the training dataset")
    p.add_argument("--out", default="outputs/fig4_cnmp.png", help="PNG to write")
    args = p.parse_args(argv)
    path = paper_figure(args.checkpoint, args.dataset, args.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

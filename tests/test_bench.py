"""The benchmark protocols' own logic (data, test draws, scores); the figures themselves live in bench/."""

import sys

import numpy as np

import bench.sine_benchmark as sine
from bench.time_to_error import first_below


def test_sine_data_follows_the_protocol():
    demos, modes, means = sine.make_sines(np.random.default_rng(0))
    assert demos.shape == (128, 200) and np.bincount(modes).tolist() == [32] * 4
    assert demos.min() >= 0.0 and demos.max() <= 1.03  # (sin + 1) / 2 plus positive noise
    # Modes 0/2 and 1/3 end at nearly the same value: the end point alone does not name the mode.
    assert abs(means[0, -1] - means[2, -1]) < 0.05 and abs(means[1, -1] - means[3, -1]) < 0.05
    assert abs(means[0, -1] - means[1, -1]) > 0.8


def test_sine_tests_sit_between_two_close_modes():
    _, _, means = sine.make_sines(np.random.default_rng(0))
    tests = sine.draw_tests(means, np.random.default_rng(1))
    assert len(tests) == sine.N_TESTS
    for k, y0 in tests:
        assert k < 150
        # y0 lies between two mode means that are within 0.1 of each other at that step
        gaps = [(a, b) for a in range(4) for b in range(4) if a < b and abs(means[a, k] - means[b, k]) < 0.1
                and min(means[a, k], means[b, k]) <= y0 <= max(means[a, k], means[b, k])]
        assert gaps
    sets = sine.condition_sets(tests, means)
    assert len(sets) == 4 * sine.N_TESTS and all(len(c) == 2 and c[1].phase == 1.0 for c in sets)


def test_nearest_demo_score():
    demos, _, _ = sine.make_sines(np.random.default_rng(0))
    assert sine.nearest_demo_error(demos[7], demos) == 0.0
    assert sine.nearest_demo_error(demos[7] + 0.1, demos) <= 0.1 + 1e-9
    assert sine.score([demos[0], demos[1] + 0.05], demos)[0] <= 0.025 + 1e-9


def test_first_below():
    pts = [(100, 1.0, 0.5), (200, 2.0, 0.02), (300, 3.0, 0.01)]
    assert first_below(pts, 0.03) == (200, 2.0)
    assert first_below(pts, 0.001) == (None, None)


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    import pytest
    from bench.common import MissingCheckpointError, resolve_checkpoint

    with pytest.raises(MissingCheckpointError, match="--train"):
        resolve_checkpoint(tmp_path / "nowhere", train=False, out_dir=tmp_path / "fit")
    (tmp_path / "run" / "pretrained_model").mkdir(parents=True)
    (tmp_path / "run" / "pretrained_model" / "config.json").write_text("{}")
    with pytest.raises(MissingCheckpointError, match="did you mean"):
        resolve_checkpoint(tmp_path / "run", train=False, out_dir=tmp_path / "fit")
    assert resolve_checkpoint(tmp_path / "run" / "pretrained_model", train=False, out_dir=tmp_path) == \
        tmp_path / "run" / "pretrained_model"


def test_provenance_of_a_lerobot_train_checkpoint(tmp_path):
    import json

    from bench.common import REPO, provenance

    cfg = json.loads((REPO / "configs" / "cnmp_obstacle2d.json").read_text())
    ckpt = tmp_path / "checkpoints" / "009000" / "pretrained_model"
    ckpt.mkdir(parents=True)
    (ckpt / "config.json").write_text("{}")
    (ckpt / "model.safetensors").write_bytes(b"weights")
    (ckpt / "train_config.json").write_text(json.dumps({**cfg, "output_dir": "outputs/x/train"}))
    (ckpt.parent / "training_state").mkdir()
    (ckpt.parent / "training_state" / "training_step.json").write_text(json.dumps({"step": 1234}))
    p = provenance(ckpt)
    assert p["step"] == 1234 and p["trained_by"] == "lerobot-train"
    assert p["training_command"] == "lerobot-train --config_path=configs/cnmp_obstacle2d.json --output_dir=outputs/x/train"
    assert len(p["weights_sha256"]) == 16
    # flags given on the command line on top of the config are part of the command
    over = {**cfg, "output_dir": "outputs/x/train",
            "policy": {**cfg["policy"], "n_experts": 2, "encoder_layers": [256, 256], "device": "cpu"}}
    (ckpt / "train_config.json").write_text(json.dumps(over))
    assert provenance(ckpt)["training_command"] == (
        "lerobot-train --config_path=configs/cnmp_obstacle2d.json --policy.encoder_layers=[256,256] "
        "--policy.n_experts=2 --output_dir=outputs/x/train")
    (ckpt / "train_config.json").write_text(json.dumps({**cfg, "seed": 7}))  # no committed config matches
    assert "no committed config matches" in provenance(ckpt)["training_command"]


def test_mode_of_reads_the_side_of_the_obstacle_where_the_path_crosses_it():
    from bench.obstacle_shared import mode_of

    x = np.linspace(0.0, 1.0, 101)
    bump = 0.3 * np.sin(np.pi * x)
    over, under = np.stack([x, bump], 1), np.stack([x, -bump], 1)
    assert mode_of(over) == "over" and mode_of(under) == "under"
    # the ends do not decide: a path that starts and ends above the obstacle's centre line but dips under it
    dip = np.stack([x, 0.05 - 0.3 * np.sin(np.pi * x)], 1)
    assert mode_of(dip) == "under"


def test_sine_benchmark_runs_end_to_end_with_the_mixture(tmp_path, monkeypatch):
    """The bench's whole path (CNMP, the mixture with a setting given, ProMP, plots, JSON) on a few steps:
    its figures are the README's, so it must run as documented (a missing import once broke it)."""
    monkeypatch.setattr(sys, "argv", ["sine_benchmark.py", "--steps", "3", "--batch_size", "4", "--experts", "2",
                                      "--assignment_draws", "1", "--plot", str(tmp_path / "a.png"),
                                      "--mixture_plot", str(tmp_path / "b.png")])
    res = sine.main()
    assert res["mixture_experts"] == 2 and res["mixture_settings"]["assignment_draws"] == 1
    assert {"sine_error_cnmp", "sine_error_mixture", "sine_error_promp"} <= set(res)
    assert (tmp_path / "a.png").stat().st_size > 0 and (tmp_path / "b.png").stat().st_size > 0


def test_mixture_cost_compares_mean_curves_over_seeds():
    """--seeds: the curves are averaged point by point (time and NLL), the single decoder's final mean NLL is
    the target, and a mixture that never gets there is 'not reached' (no ratio), not a number."""
    import bench.mixture_cost as mc

    cnmp = [[(1, 1.0, -1.0), (2, 2.0, -2.0)], [(1, 3.0, -3.0), (2, 4.0, -4.0)]]
    mean = mc.mean_curve(cnmp)
    assert mean == [(1, 2.0, -2.0), (2, 3.0, -3.0)]
    res = mc.compare({"cnmp": mean, "mixture": [(1, 4.0, -2.5), (2, 6.0, -3.5)]})
    assert res["target_validation_nll"] == -3.0 and res["steps_to_target_mixture"] == 2
    assert res["time_ratio_mixture_vs_cnmp"] == 2.0  # 6 s against 3 s
    res = mc.compare({"cnmp": mean, "mixture": [(1, 4.0, -2.5), (2, 6.0, -2.9)]})
    assert res["time_to_target_s_mixture"] is None and "time_ratio_mixture_vs_cnmp" not in res
    try:
        mc.mean_curve([cnmp[0], cnmp[1][:1]])  # runs of different lengths cannot be averaged
    except ValueError:
        pass
    else:
        raise AssertionError("curves of different lengths were averaged")


def test_mixture_cost_runs_end_to_end_over_two_seeds(monkeypatch, capsys):
    """The bench's whole path (both models per seed, mean curves, per-seed verdicts, JSON) on a few steps."""
    import json

    import bench.mixture_cost as mc

    monkeypatch.setattr(sys, "argv", ["mixture_cost.py", "--experts", "2", "--steps", "4", "--every", "2",
                                      "--validation", "2", "--seeds", "0", "1", "--assignment_draws", "1"])
    res = mc.main()
    assert res["seeds"] == [0, 1] and [s["seed"] for s in res["per_seed"]] == [0, 1]
    assert res["assignment_draws"] == 1 and res["steps_to_target_cnmp"] == 4
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == json.loads(json.dumps(res))


def test_mixture_arguments_cover_every_mixture_setting():
    """Every bench that takes the mixture's settings gets each of MIXTURE_FIELDS as an option (None: the
    config's), and only those given reach the model."""
    import argparse

    from bench.common import MIXTURE_FIELDS, add_mixture_arguments, mixture_settings

    p = argparse.ArgumentParser()
    add_mixture_arguments(p)
    args = p.parse_args([])
    assert {k for k, v in vars(args).items() if v is None} == set(MIXTURE_FIELDS) and mixture_settings(args) == {}
    args = p.parse_args(["--assignment_draws", "1", "--unconditional_nll_coef", "0.25"])
    assert mixture_settings(args) == {"assignment_draws": 1, "unconditional_nll_coef": 0.25}


def test_settings_reader_derives_options_from_a_dataclass():
    """add_dataclass_arguments: one option per field, its type from the annotation (int, float, bool, str,
    ``X | None``, ``tuple[X, ...]``, ``Literal``), default None; dataclass_settings returns those given."""
    import argparse
    import dataclasses
    from typing import Literal

    import pytest

    from bench.settings import add_dataclass_arguments, dataclass_settings

    @dataclasses.dataclass
    class Section:
        flag: bool = False

    @dataclasses.dataclass
    class Demo:
        steps: int = 3
        rate: float | None = None
        name: str = "a"
        on: bool = True
        layers: tuple[int, ...] = (8, 8)
        form: Literal["x", "y"] = "x"
        section: Section = dataclasses.field(default_factory=Section)

    p = argparse.ArgumentParser()
    add_dataclass_arguments(p, Demo, choices={"name": ("a", "b")})
    assert dataclass_settings(p.parse_args([]), Demo) == {}
    args = p.parse_args(["--steps", "5", "--rate", "0.5", "--on", "false", "--layers", "4", "2", "--form", "y"])
    assert dataclass_settings(args, Demo) == {"steps": 5, "rate": 0.5, "on": False, "layers": (4, 2), "form": "y"}
    assert "section" not in vars(args)  # a nested section has no flat option
    for bad in (["--name", "c"], ["--form", "z"], ["--steps", "x"], ["--on", "maybe"]):
        with pytest.raises(SystemExit):
            p.parse_args(bad)
    only = argparse.ArgumentParser()
    add_dataclass_arguments(only, Demo, only=("rate",))
    assert set(vars(only.parse_args([]))) == {"rate"}
    with pytest.raises(ValueError, match="no field"):
        add_dataclass_arguments(argparse.ArgumentParser(), Demo, only=("nope",))
    with pytest.raises(TypeError, match="no command-line form"):
        add_dataclass_arguments(argparse.ArgumentParser(), Demo, only=("section",))


def test_mixture_options_take_the_configs_types_and_choices():
    import argparse

    import pytest

    from bench.common import add_mixture_arguments, mixture_settings
    from lerobot_cnmp.policy.configuration_cnmp import EXPERT_SELECTION

    p = argparse.ArgumentParser()
    add_mixture_arguments(p)
    assert mixture_settings(p.parse_args(["--expert_selection", EXPERT_SELECTION[-1]])) == {
        "expert_selection": EXPERT_SELECTION[-1]}
    with pytest.raises(SystemExit):
        p.parse_args(["--expert_selection", "nonsense"])
    with pytest.raises(SystemExit):
        p.parse_args(["--mixture_nll", "assigned"])  # removed: only the assigned loss remains
    with pytest.raises(SystemExit):
        p.parse_args(["--assignment_draws", "1.5"])


def test_api_model_takes_every_model_setting_of_the_config():
    """api_model passes the config's CNMPConfig fields (not LeRobot's own, not the ones the API sets from the
    demos) and refuses an image config instead of dropping use_images."""
    import pytest

    from bench.common import api_model, config

    cfg = config()
    extra = {"nll_beta": 0.5, "encoder_layers": [64, 64], "device": "cpu", "state_tracks_action": True,
             "execution": {"pd_kp": 0.5}}
    model = api_model({**cfg, "policy": {**cfg["policy"], **extra}})
    got = model.overrides
    assert got["nll_beta"] == 0.5 and tuple(got["encoder_layers"]) == (64, 64) and got["execution"].pd_kp == 0.5
    assert got["sampling"].n_max_context == cfg["policy"]["sampling"]["n_max_context"]
    assert not {"device", "state_tracks_action", "type", "push_to_hub"} & set(got)
    with pytest.raises(ValueError, match="not images"):
        api_model({**cfg, "policy": {**cfg["policy"], "use_images": True}})


def test_training_comparisons_run_both_sides_with_the_same_threads():
    """train_speed / time_to_error: --threads, else OMP_NUM_THREADS, else the cores, for the API (this process)
    and for lerobot-train (its OMP_NUM_THREADS); a bad value is an error, not a silent default."""
    import os

    import pytest

    from bench.common import child_environment, torch_threads

    assert torch_threads(None, {"OMP_NUM_THREADS": "3"}) == (3, "OMP_NUM_THREADS")
    assert torch_threads(2, {"OMP_NUM_THREADS": "5"}) == (2, "--threads")
    assert torch_threads(None, {}) == (os.cpu_count() or 1, "CPU cores")
    for bad, env in ((None, {"OMP_NUM_THREADS": "two"}), (0, {}), (None, {"OMP_NUM_THREADS": "0"})):
        with pytest.raises(ValueError, match="threads|OMP_NUM_THREADS"):
            torch_threads(bad, env)
    env = child_environment(2, {"OMP_NUM_THREADS": "5", "PATH": "/bin"})
    assert env["OMP_NUM_THREADS"] == "2" and env["PATH"] == "/bin" and env["HF_HUB_OFFLINE"] == "1"


def test_no_bench_edits_sys_path():
    """Every bench is a module of the ``bench`` package run as ``python -m bench.<name>``: none inserts a
    folder into sys.path (nor builds child code that does), each runnable one's usage line says how to run it
    (the shared modules, with no ``__main__`` block, are imported by the benches)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "bench"
    for path in sorted(root.glob("*.py")):
        text = path.read_text()
        assert "sys.path" not in text, path.name
        if 'if __name__ == "__main__"' in text:
            assert f"python -m bench.{path.stem}" in text, path.name


def test_camera_probe_r2_finds_a_linear_code_and_not_noise():
    from bench.camera_probe import loo_r2

    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 6))
    y = np.c_[x @ rng.normal(size=6), rng.normal(size=50), np.full(50, 0.3)]
    r2 = loo_r2(x, y)
    assert r2[0] > 0.99 and r2[1] < 0.2 and r2[2] is None


def test_camera_probe_heldout_r2_scores_new_scenes_with_the_fit_on_the_dataset():
    """The held-out R² fits on the dataset's episodes and scores the fresh scenes: a linear code generalizes
    (R² near 1), an entry fitted only by chance does not, and a constant entry has none."""
    from bench.camera_probe import heldout_r2

    rng = np.random.default_rng(1)
    w = rng.normal(size=6)
    x, x_new = rng.normal(size=(50, 6)), rng.normal(size=(40, 6))
    y = np.c_[x @ w, rng.normal(size=50), np.full(50, 0.3)]
    y_new = np.c_[x_new @ w, rng.normal(size=40), np.full(40, 0.3)]
    r2 = heldout_r2(x, y, x_new, y_new)
    assert r2[0] > 0.99 and r2[1] < 0.2 and r2[2] is None
    assert heldout_r2(x, y, x_new, -y_new)[0] < 0  # scored against the new scenes' values, not refitted

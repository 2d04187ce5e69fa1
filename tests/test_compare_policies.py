"""bench/compare_policies.py without training: which cells run (resume / --force / error cells), that a
failing cell is recorded as an error and ends the run non-zero, and the report (table, plot) on fake result
files."""

import json
from pathlib import Path

import pytest

import bench.compare_policies as cp


def _ok(task, method, n, pc):
    return {"task": task, "method": method, "n_demos": n, "status": "ok", "pc_success": pc, "n_episodes": 50,
            "steps": cp.STEPS[method], "train_wall_s": 100.0, "train_peak_rss_mb": 900.0,
            "select_action_p50_ms": 0.8, "select_action_p95_ms": 3.5, "step_with_processors_p50_ms": 1.2, "date": "2026-12-02T03:00:00",
            "budget_rule": cp.BUDGET_RULE}


def _write(out, rec):
    path = cp.result_path(out, rec["task"], rec["method"], rec["n_demos"])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec))
    return path


def test_should_run_resume_force_and_errors(tmp_path):
    missing = cp.result_path(tmp_path, "cnmp_obstacle2d", "act", 5)
    assert cp.should_run(missing, force=False)
    ok = _write(tmp_path, _ok("cnmp_obstacle2d", "act", 5, 40.0))
    assert not cp.should_run(ok, force=False)
    assert cp.should_run(ok, force=True)
    err = _write(tmp_path, {"task": "cnmp_obstacle2d", "method": "cnmp", "n_demos": 5, "status": "error",
                            "error": "CellError: lerobot-train failed"})
    assert cp.should_run(err, force=False)  # an error cell is run again
    broken = cp.result_path(tmp_path, "cnmp_obstacle2d", "diffusion", 5)
    broken.write_text("{not json")
    assert cp.should_run(broken, force=False)


def test_run_skips_done_cells_and_records_failures(tmp_path, monkeypatch):
    _write(tmp_path, _ok("cnmp_obstacle2d", "cnmp", 5, 100.0))
    calls = []

    def fake_cell(task, method, n, **kw):
        calls.append((task, method, n))
        if method == "act":
            raise cp.CellError("lerobot-eval failed (exit 1)", {"train_command": "lerobot-train ..."})
        return _ok(task, method, n, 10.0 * n)

    monkeypatch.setattr(cp, "run_cell", fake_cell)
    args = ["--tasks", "cnmp_obstacle2d", "--methods", "cnmp", "act", "--demos", "5", "10", "--out", str(tmp_path)]
    assert cp.main(args) == 1  # the act cells failed: non-zero, not a silent skip
    assert calls == [("cnmp_obstacle2d", "act", 5), ("cnmp_obstacle2d", "cnmp", 10), ("cnmp_obstacle2d", "act", 10)]
    err = json.loads(cp.result_path(tmp_path, "cnmp_obstacle2d", "act", 5).read_text())
    assert err["status"] == "error" and "lerobot-eval failed" in err["error"]
    assert err["train_command"] == "lerobot-train ..."
    assert json.loads(cp.result_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5).read_text())["pc_success"] == 100.0

    calls.clear()
    monkeypatch.setattr(cp, "run_cell", lambda task, method, n, **kw: calls.append((method, n)) or _ok(task, method, n, 1.0))
    assert cp.main(args) == 0  # only the two error cells run again
    assert calls == [("act", 5), ("act", 10)]
    calls.clear()
    assert cp.main(args + ["--force"]) == 0
    assert len(calls) == 4


def test_a_tasks_own_steps_and_the_override(tmp_path, monkeypatch):
    """cnmp_so101's CNMP (twice as wide) gets the task's 4500 steps; --steps overrides a task's steps too."""
    seen = []
    monkeypatch.setattr(cp, "run_cell", lambda task, method, n, steps, **kw: seen.append((method, steps))
                        or _ok(task, method, n, 1.0))
    base = ["--tasks", "cnmp_so101", "--methods", "cnmp", "act", "--demos", "10", "--out", str(tmp_path)]
    assert cp.main(base) == 0
    assert seen == [("cnmp", 4500), ("act", cp.STEPS["act"])]
    seen.clear()
    assert cp.main(base + ["--force", "--steps", "cnmp=100"]) == 0
    assert seen == [("cnmp", 100), ("act", cp.STEPS["act"])]


def test_steps_override_is_checked(tmp_path):
    with pytest.raises(SystemExit):
        cp.main(["--tasks", "cnmp_obstacle2d", "--steps", "nope=3", "--out", str(tmp_path)])


def test_report_table_and_plot(tmp_path):
    for method, pcs in (("cnmp", (90.0, 100.0)), ("act", (20.0, 44.0))):
        for n, pc in zip((5, 10), pcs, strict=True):
            _write(tmp_path, _ok("cnmp_obstacle2d", method, n, pc))
    _write(tmp_path, _ok("cnmp_metaworld_reach", "cnmp", 5, 70.0))
    _write(tmp_path, {"task": "cnmp_metaworld_reach", "method": "diffusion", "n_demos": 5, "status": "error",
                      "error": "CellError: lerobot-train failed (exit 1)\nTraceback ..."})
    plot = tmp_path / "plot.png"
    text = cp.report(tmp_path, plot)
    summary, every = text.split("Every cell:")
    # the summary: one row per task and demos, a column per method with pc_success (training seconds)
    assert "| task | demos | cnmp | act | diffusion |" in summary
    assert "| cnmp_obstacle2d | 10 | 100 (100 s) | 44 (100 s) | – |" in summary
    assert "| cnmp_metaworld_reach | 5 | 70 (100 s) | – | err |" in summary
    rows = [line for line in every.splitlines() if line.startswith("| cnmp_")]
    assert len(rows) == 6
    assert rows[0].startswith("| cnmp_obstacle2d | cnmp | 5 | 90.0 | 50 |")  # the tasks in TASKS' order
    assert rows[4].startswith("| cnmp_metaworld_reach | cnmp | 5 | 70.0 | 50 |")
    assert "| 0.800 / 3.50 | 1.200 |" in rows[0]
    assert "| cnmp_metaworld_reach | diffusion | 5 | **error**: CellError: lerobot-train failed (exit 1) |" in text
    assert "| cnmp_obstacle2d | act | 10 | 44.0 |" in text
    # methods in the table's order: cnmp before act for the same task and demos
    obstacle = [r for r in rows if r.startswith("| cnmp_obstacle2d")]
    assert [r.split("|")[2].strip() for r in obstacle] == ["cnmp", "act", "cnmp", "act"]
    assert plot.is_file() and plot.stat().st_size > 1000
    assert (tmp_path / "report.md").read_text() == text
    assert plot.with_suffix(".md").read_text() == text  # the committed copy beside the plot


def test_report_without_results_is_an_error(tmp_path):
    with pytest.raises(SystemExit):
        cp.report(tmp_path, tmp_path / "p.png")


def test_commands(tmp_path):
    ckpt = tmp_path / "ckpt"
    cmd = cp.train_command("cnmp_obstacle2d", "act", 3, 900, tmp_path / "train", None)
    assert "--dataset.episodes=[0,1,2]" in cmd and "--steps=900" in cmd
    assert "--config_path=configs/act_cpu_obstacle2d.json" in cmd
    ev = cp.eval_command("cnmp_metaworld_reach", "act", ckpt, 50, 10, tmp_path / "eval")
    assert f"--seed={cp.SEED}" in ev and "--eval.n_episodes=50" in ev
    assert any(a.startswith("--rename_map=") for a in ev)
    assert not any(a.startswith("--rename_map=") for a in cp.eval_command("cnmp_metaworld_reach", "cnmp", ckpt, 50, 10,
                                                                            tmp_path))
    for task in cp.TASKS.values():
        for config in task["configs"].values():
            assert (cp.REPO / config).is_file(), config


def test_a_tasks_episode_order(tmp_path):
    """cnmp_pickplace's cells take its grid's corners first; a task without an order takes 0..N-1; every order
    is a permutation of its dataset's episodes."""
    assert cp.episodes("cnmp_obstacle2d", 3) == [0, 1, 2]
    assert cp.episodes("cnmp_pickplace", 5) == [0, 7, 3, 4, 1]
    cmd = cp.train_command("cnmp_pickplace", "act", 5, 900, tmp_path / "train", None)
    assert "--dataset.episodes=[0,7,3,4,1]" in cmd
    for name, task in cp.TASKS.items():
        if "episode_order" in task:
            total = json.loads((cp.REPO / task["dataset"] / "meta" / "info.json").read_text())["total_episodes"]
            assert sorted(task["episode_order"]) == list(range(total)), name


def test_promp_cell_where_it_cannot_condition_is_an_error(tmp_path):
    with pytest.raises(cp.CellError, match="ProMP is not set up"):
        cp.run_cell("cnmp_so101", "promp", 5, out=tmp_path, steps=0, n_episodes=2, batch_size=1)


def test_report_labels_in_process_rows(tmp_path):
    _write(tmp_path, _ok("cnmp_obstacle2d", "cnmp", 5, 90.0))
    _write(tmp_path, {**_ok("cnmp_obstacle2d", "cnmp", 5, 60.0), "method": "promp", "steps": 0,
                      "label": cp.PROMP_LABEL, "select_action_p50_ms": None})
    text = cp.report(tmp_path, tmp_path / "p.png")
    assert "| cnmp_obstacle2d | promp (open loop†) | 5 | 60.0 |" in text
    assert "† " + cp.PROMP_LABEL in text


def test_train_loop_time_from_the_log(tmp_path):
    log = tmp_path / "train.log"
    log.write_text("Training:  50%|#####     | 450/900 [00:59<00:59, 7.5step/s]\rTraining: 100%|##########| "
                   "900/900 [02:03<00:00, 7.31step/s]\nINFO End of training\n")
    assert cp.train_loop_s(log) == 123.0
    log.write_text("Training:  50%|#####     | 450/900 [00:59<00:59, 7.5step/s]\nTraceback ...\n")
    assert cp.train_loop_s(log) is None
    assert cp.train_loop_s(tmp_path / "missing.log") is None


def test_promp_cells_fit_with_the_cli_and_evaluate_with_lerobot_eval(tmp_path):
    # ProMP's "training" is the closed-form fit on the cell's episodes; its evaluation is the same lerobot-eval
    fit = cp.fit_command("cnmp_pickplace", 2, tmp_path / "train")
    assert Path(fit[0]).name == "lerobot-cnmp-fit-promp"
    assert "--episodes=0,7" in fit and "--conditioning=task_params" in fit  # the grid corners first
    assert cp.fit_command("cnmp_obstacle2d", 3, tmp_path)[3] == "--conditioning=conditions"
    ev = cp.eval_command("cnmp_metaworld_pickplace", "promp", tmp_path / "ckpt", 50, 10, tmp_path / "eval")
    assert Path(ev[0]).name == "lerobot-eval" and "--env.task=pick-place-v3" in ev
    assert not any(a.startswith("--rename_map=") for a in ev)  # ProMP reads γ under CNMP's name


def test_methods_without_cells_on_a_task_are_skipped_with_the_reason(tmp_path, monkeypatch, capsys):
    """cnmp_weights has CNMP and ProMP cells only: ACT / Diffusion are skipped (printed, no file, exit 0)."""
    real_run_cell, calls = cp.run_cell, []
    monkeypatch.setattr(cp, "run_cell", lambda task, method, n, **kw: calls.append(method) or _ok(task, method, n, 1.0))
    args = ["--tasks", "cnmp_weights", "--methods", "cnmp", "act", "diffusion", "promp", "--demos", "10",
            "--out", str(tmp_path)]
    assert cp.main(args) == 0
    assert calls == ["cnmp", "promp"]
    assert "validate_features" in capsys.readouterr().out
    assert not cp.result_path(tmp_path, "cnmp_weights", "act", 10).exists()
    with pytest.raises(cp.CellError, match="act has no cell on cnmp_weights"):
        real_run_cell("cnmp_weights", "act", 10, out=tmp_path, steps=1, n_episodes=2, batch_size=1)

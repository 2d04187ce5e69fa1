"""bench.compare_policies without training: the cells' commands and schedule, resume of a cut training and of
finished seeds, failures recorded as errors (exit 1), and the report's best / time-to-90 % / mean / spread
computed from fake lerobot-train logs and fake lerobot-eval files."""

import json
from unittest import mock
from pathlib import Path

import pytest

import bench.compare_cells as cells
import bench.compare_policies as cp
import bench.compare_report as rep
import bench.compare_run as run

RATE = 10.0  # the fake lerobot-train's steps per second of training loop
# the fake lerobot-eval's pc_success: curve (seed 200000, by checkpoint step) and held-out (seed 100000)
CURVE = {1000: {300: 20.0, 600: 60.0, 1200: 55.0}, 1001: {300: 50.0, 600: 70.0, 1200: 80.0},
         1002: {300: 90.0, 600: 90.0, 1200: 90.0}}
HELDOUT = {1000: 50.0, 1001: 70.0, 1002: 80.0}


def _arg(cmd, name):
    return next(a.split("=", 1)[1] for a in cmd if a.startswith(f"--{name}="))


class FakeCLIs:
    """Stands in for run_logged: writes what lerobot-train / lerobot-eval / lerobot-cnmp-fit-promp would."""

    def __init__(self, cut_after=None):
        self.cut_after, self.commands = cut_after, []

    def __call__(self, cmd, log, env, poll=None):
        self.commands.append(cmd)
        log.parent.mkdir(parents=True, exist_ok=True)
        tool = Path(cmd[0]).name
        if tool == "lerobot-train":
            rc = self.train(cmd, log)
        elif tool == "lerobot-eval":
            rc = self.eval(cmd, log)
        else:
            out = Path(_arg(cmd, "output_dir"))
            (out / "pretrained_model").mkdir(parents=True)
            (out / "pretrained_model" / "config.json").write_text("{}")
            (out / "fit_info.json").write_text(json.dumps({"fit_s": 0.7, "command": "fit"}))
            log.write_text("fitted\n")
            rc = 0
        if poll:
            poll()
        return {"rc": rc, "wall_s": 1.0, "peak_rss_mb": 100.0}

    def train(self, cmd, log):
        if "--resume=true" in cmd:
            cfg_file = Path(_arg(cmd, "config_path"))
            cfg = json.loads(cfg_file.read_text())
            start = json.loads((cfg_file.parents[1] / "training_state" / "training_step.json").read_text())["step"]
            if any(a.startswith("--steps=") for a in cmd):
                cfg["steps"] = int(_arg(cmd, "steps"))
        else:
            cfg = {"steps": int(_arg(cmd, "steps")), "save_freq": int(_arg(cmd, "save_freq")),
                   "output_dir": _arg(cmd, "output_dir"), "seed": int(_arg(cmd, "seed")), "dataset": {"root": "d"}}
            start = 0
        total, root = cfg["steps"], Path(cfg["output_dir"]) / "checkpoints"
        bars, saved = [], 0
        stride = max(1, (total - start) // 20)  # the bar updates between checkpoints too
        for step in range(start + 1, total + 1):
            done = step - start
            if done % stride == 0 or step % cfg["save_freq"] == 0:
                t = round(done / RATE)
                bars.append(f"Training: {100 * done // (total - start)}%|##| {done}/{total - start} "
                            f"[{t // 60:02d}:{t % 60:02d}<00:10, {RATE}step/s]")
            if step % cfg["save_freq"]:
                continue
            ck = root / f"{step:06d}"
            (ck / "pretrained_model").mkdir(parents=True)
            (ck / "pretrained_model" / "config.json").write_text("{}")
            (ck / "pretrained_model" / "train_config.json").write_text(json.dumps(cfg))
            (ck / "training_state").mkdir()
            (ck / "training_state" / "training_step.json").write_text(json.dumps({"step": step}))
            (root / "last").unlink(missing_ok=True)
            (root / "last").symlink_to(ck.name)
            saved += 1
            if self.cut_after is not None and saved >= self.cut_after:
                log.write_text("\r".join(bars) + "\nKilled\n")
                self.cut_after = None
                return 137
        log.write_text("\r".join(bars) + "\nINFO End of training\n")
        return 0

    def eval(self, cmd, log):
        ckpt, seed, n = Path(_arg(cmd, "policy.path")), int(_arg(cmd, "seed")), int(_arg(cmd, "eval.n_episodes"))
        train_seed = int(next(p.name for p in ckpt.parents if p.name.startswith("seed"))[4:])
        if "checkpoints" in ckpt.parts:
            step = int(ckpt.parent.name)
        else:
            step = 0  # ProMP's single fit
        pc = HELDOUT[train_seed] if seed == cells.SEED else CURVE[train_seed].get(step, 33.0)
        out = Path(_arg(cmd, "output_dir"))
        out.mkdir(parents=True)
        (out / "eval_info.json").write_text(json.dumps({"overall": {"pc_success": pc, "n_episodes": n}}))
        log.write_text("eval\n")
        return 0


ARGS = ["--tasks", "cnmp_obstacle2d", "--methods", "cnmp", "--demos", "5", "--marks", "30", "60", "120",
        "--cap", "cnmp=120", "--no_latency", "--curve_episodes", "4", "--n_episodes", "6"]


@pytest.fixture
def fake(monkeypatch):
    clis = FakeCLIs()
    monkeypatch.setattr(run, "run_logged", clis)
    monkeypatch.setattr(run, "run_provenance", lambda: {"commit": "abc", "command": "test", "date": "2027-01-01"})
    return clis


def test_a_cached_rate_is_reused_only_for_the_same_config(tmp_path, fake, monkeypatch):
    args = ("cnmp_obstacle2d", "cnmp", 5, 1000, tmp_path, None, {})
    first = run.step_rate(*args)
    assert first["config_sha256"] == run.config_digest("cnmp_obstacle2d", "cnmp") and len(fake.commands) == 1
    assert run.step_rate(*args) == first and len(fake.commands) == 1  # cached
    assert run.config_digest("cnmp_obstacle2d", "cnmp_noterm") != first["config_sha256"]  # variant args count
    monkeypatch.setattr(run, "config_digest", lambda task, method: "another config")
    assert run.step_rate(*args)["config_sha256"] == "another config" and len(fake.commands) == 2  # probed again


def test_curves_seeds_and_the_report_from_fake_eval_files(tmp_path, fake):
    assert cp.main([*ARGS, "--out", str(tmp_path)]) == 0
    rates = json.loads((tmp_path / "rates.json").read_text())["cnmp_obstacle2d/cnmp"]
    assert rates["steps_per_s"] == RATE and rates["probe_steps"] == cells.PROBE_STEPS["cnmp"]
    for seed in (1000, 1001, 1002):  # CNMP's default: 3 training seeds, each trained once with its --seed
        rec = json.loads(cells.record_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5, seed).read_text())
        assert rec["status"] == "ok" and rec["schedule"]["marks"] == {"30": 300, "60": 600, "120": 1200}
        assert f"--seed={seed}" in rec["train"]["attempts"][0]["command"]
        assert [(p["step"], p["loop_s"], p["n_episodes"]) for p in rec["points"]] == [(300, 30.0, 4), (600, 60.0, 4),
                                                                                       (1200, 120.0, 4)]
        assert all(p["provenance"]["commit"] == "abc" and p["eval_command"] for p in rec["points"])  # provenance per point
        assert rec["heldout"]["n_episodes"] == 6 and f"--seed={cells.SEED}" in rec["heldout"]["eval_command"]
        # the checkpoint between marks (900) was deleted once a later one existed
        assert run.checkpoint_steps(cells.record_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5, seed).with_suffix("")
                                    / "train") == [300, 600, 1200]
    recs = rep.load_records(tmp_path)
    seeds = {s["seed"]: s for s in (rep.seed_summary(r) for r in recs)}
    assert (seeds[1000]["curve_max"], seeds[1000]["t90_s"], seeds[1000]["best_step"]) == (60.0, 60.0, 600)
    assert (seeds[1001]["t90_s"], seeds[1001]["best_step"]) == (120.0, 1200)
    assert (seeds[1002]["t90_s"], seeds[1002]["best_step"]) == (30.0, 300)  # a tie: the earliest checkpoint
    (cell,) = rep.cell_summaries(recs)
    assert cell["n_seeds"] == 3
    assert cell["best"] == {"mean": pytest.approx(200 / 3), "min": 50.0, "max": 80.0, "n": 3}
    assert cell["t90_s"] == {"mean": 70.0, "min": 30.0, "max": 120.0, "n": 3}
    assert cell["at_2min"]["mean"] == pytest.approx(75.0)
    assert cell["mean_curve"][0] == [30.0, pytest.approx(160 / 3), 20.0, 90.0]
    text = rep.report(tmp_path, tmp_path / "docs" / "cmp.png")
    assert "| cnmp_obstacle2d | 5 | 67 [50–80] (3 seeds) · 70 [30–120] s |" in text
    assert "cnmp: 3" in text
    assert (tmp_path / "docs" / "compare_curves_cnmp_obstacle2d.png").stat().st_size > 1000
    assert (tmp_path / "docs" / "cmp.png").is_file() and json.loads((tmp_path / "curves.json").read_text())["cells"]

    n = len(fake.commands)
    assert cp.main([*ARGS, "--out", str(tmp_path)]) == 0  # a rerun skips what is done
    assert len(fake.commands) == n


def test_a_cut_training_resumes_and_keeps_its_clock(tmp_path, fake):
    fake.cut_after = 2  # killed after the checkpoints at 300 and 600
    args = [*ARGS, "--seeds", "1001", "--out", str(tmp_path)]
    assert cp.main(args) == 1  # the cut is an error: non-zero, recorded
    path = cells.record_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5, 1001)
    rec = json.loads(path.read_text())
    assert rec["status"] == "error" and "lerobot-train failed (exit 137)" in rec["error"]
    assert rec["train"]["checkpoint_loop_s"] == {"300": 30.0, "600": 60.0}
    assert cp.main(args) == 0
    rec = json.loads(path.read_text())
    resumed = rec["train"]["attempts"][1]
    assert "--resume=true" in resumed["command"] and resumed["start_step"] == 600
    assert rec["train"]["checkpoint_loop_s"]["1200"] == 120.0  # 60 s before the cut + 60 s after the resume
    assert rec["heldout"]["step"] == 1200 and rec["heldout"]["pc_success"] == 70.0
    assert rec["status"] == "ok" and "error" not in rec
    probes = [c for c in fake.commands if "rate_probes" in " ".join(c)]
    assert len(probes) == 1  # the rate is measured once per task and method


def test_a_resume_from_a_pruned_checkpoint_keeps_its_clock(tmp_path):
    """The checkpoint a run was cut at (not a mark, pruned once later ones exist) still times the resumed
    attempt: its steps' loop seconds continue from the cut."""
    bar = "Training: {p}%|##| {n}/{total} [00:{t:02d}<00:10, 10step/s]"
    first, second = tmp_path / "train.log", tmp_path / "train1.log"
    first.write_text("\r".join(bar.format(p=k * 10, n=k * 100, total=1000, t=k * 10 // 10) for k in (1, 3, 5)) + "\nKilled")
    second.write_text("\r".join(bar.format(p=k * 20, n=k * 100, total=500, t=k * 10 // 10) for k in (1, 3, 5)))
    attempts = [{"start_step": 0, "log": str(first)}, {"start_step": 500, "log": str(second)}]
    assert run.checkpoint_times(attempts, [300, 1000]) == {"300": 3.0, "500": 5.0, "1000": 10.0}


def test_an_act_run_the_probe_under_counted_is_extended_to_its_cap(tmp_path, fake):
    """ACT (no learning-rate schedule) scheduled at half its real rate ends at half its cap: it resumes with
    --steps for the whole cap at its measured rate, and the marks it had not reached become checkpoints."""
    args = ["--tasks", "cnmp_obstacle2d", "--methods", "act", "--demos", "5", "--marks", "30", "60", "120",
            "--cap", "act=120", "--no_latency", "--curve_episodes", "4", "--n_episodes", "6", "--rate", "act=5"]
    assert cp.main([*args, "--out", str(tmp_path)]) == 0
    rec = json.loads(cells.record_path(tmp_path, "cnmp_obstacle2d", "act", 5, 1000).read_text())
    sched = rec["schedule"]
    assert sched["extended"]["from_steps"] == 600 and sched["extended"]["from_loop_s"] == 60
    assert sched["steps"] == 1200 and rec["train"]["loop_s"] == 120
    resumed = [c for c in fake.commands if "--resume=true" in c]
    assert len(resumed) == 1 and "--steps=1200" in resumed[0]
    assert [p["loop_s"] for p in rec["points"]] == [15, 30, 60, 120]  # 30, 60, 120 s marks at 5 steps/s, + the cap
    # CNMP's schedule (a learning-rate decay over --steps) is never extended
    cnmp = [{"act": "cnmp", "act=120": "cnmp=120", "act=5": "cnmp=5"}.get(a, a) for a in args]
    assert cp.main([*cnmp, "--out", str(tmp_path)]) == 0
    rec = json.loads(cells.record_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5, 1000).read_text())
    assert "extended" not in rec["schedule"] and rec["train"]["loop_s"] == 60


def test_a_seed_that_failed_in_its_probe_resumes(tmp_path, fake):
    """A record written by a failure before any curve point (a missing package in the rate probe) resumes."""
    path = cells.record_path(tmp_path, "cnmp_obstacle2d", "cnmp", 5, 1000)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"task": "cnmp_obstacle2d", "status": "error", "error": "ImportError: diffusers"}))
    assert cp.main([*ARGS, "--seeds", "1000", "--out", str(tmp_path)]) == 0
    rec = json.loads(path.read_text())
    assert rec["status"] == "ok" and len(rec["points"]) == 3
    assert "error" not in rec  # the resumed seed's record does not keep the failure it recovered from


def test_promp_is_one_fit_and_one_point(tmp_path, fake):
    assert cp.main(["--tasks", "cnmp_obstacle2d", "--methods", "promp", "--demos", "5", "--no_latency",
                    "--curve_episodes", "4", "--n_episodes", "6", "--out", str(tmp_path)]) == 0
    (rec,) = rep.load_records(tmp_path)
    assert rec["seed"] == cells.FIRST_SEED and [(p["step"], p["loop_s"]) for p in rec["points"]] == [(0, 0.7)]
    assert "deterministic" in rep.report(tmp_path, tmp_path / "p.png")


def test_the_rate_is_taken_after_the_warm_up(tmp_path):
    """A bar whose first 20 s run 1 step/s and the rest 10 steps/s: the steady rate is 10, not the mean."""
    log = tmp_path / "train.log"
    pts = [(s, s) for s in range(0, 21, 5)] + [(20 + 10 * (t - 20), t) for t in range(25, 81, 5)]
    total = pts[-1][0]
    log.write_text("\r".join(f"Training: {100 * n // total}%|##| {n}/{total} [{t // 60:02d}:{t % 60:02d}<00:01, 1step/s]"
                             for n, t in pts))
    assert run.steady_rate(log) == pytest.approx(10.0)
    assert total / run.train_loop_s(log) < 8  # the mean rate would under-count the steps of a cap


def test_schedule_puts_every_mark_on_a_saved_step():
    s = cells.schedule(7.4, 1800)
    assert s["save_freq"] == 222 and s["steps"] == 222 * 60
    assert all(step % s["save_freq"] == 0 for step in s["marks"].values())
    assert list(s["marks"]) == ["30", "60", "120", "300", "600", "1200", "1800"]  # the 2-minute point is one of them
    assert cells.schedule(100.0, 90, (30, 60, 120))["marks"] == {"30": 3000, "60": 6000, "90": 9000}
    with pytest.raises(ValueError):
        cells.schedule(0.0, 60)


def test_seeds_per_method():
    assert cells.seeds_for("cnmp", None, cells.N_SEEDS) == [1000, 1001, 1002]
    assert cells.seeds_for("act", None, cells.N_SEEDS) == [1000]
    assert cells.seeds_for("act", [0, 1, 2], cells.N_SEEDS) == [0, 1, 2]
    assert cells.seeds_for("promp", [0, 1, 2], cells.N_SEEDS) == [0]  # one closed-form fit


@pytest.mark.parametrize("bad", ["nope=3", "cnmp=-1", "cnmp=x"])
def test_method_options_are_checked(tmp_path, bad):
    with pytest.raises(SystemExit):
        cp.main(["--tasks", "cnmp_obstacle2d", "--cap", bad, "--out", str(tmp_path)])


def test_a_missing_package_stops_the_run_before_any_cell(monkeypatch, tmp_path, fake):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "diffusers" else real(name))
    with pytest.raises(SystemExit, match="diffusers not installed"):
        cp.main(["--tasks", "cnmp_metaworld_push", "--methods", "cnmp", "diffusion", "--out", str(tmp_path)])
    assert not fake.commands


def test_a_method_without_cells_on_the_tasks_needs_no_package(monkeypatch):
    """cnmp_weights has no Diffusion cells: a missing diffusers does not stop it (it stops push, which has them)."""
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "diffusers" else real(name))
    cp.check_installed(["cnmp_weights"], ["cnmp", "diffusion"])
    with pytest.raises(SystemExit, match="diffusers"):
        cp.check_installed(["cnmp_weights", "cnmp_metaworld_push"], ["cnmp", "diffusion"])


def test_report_without_results_is_an_error(tmp_path):
    with pytest.raises(SystemExit):
        rep.report(tmp_path, tmp_path / "p.png")


def test_commands(tmp_path):
    ckpt = tmp_path / "ckpt"
    sched = cells.schedule(7.4, 1800)
    cmd = cells.train_command("cnmp_obstacle2d", "act", 3, 7, sched, tmp_path / "train")
    assert "--dataset.episodes=[0,1,2]" in cmd and f"--steps={sched['steps']}" in cmd and "--seed=7" in cmd
    assert f"--save_freq={sched['save_freq']}" in cmd and "--config_path=configs/act_cpu_obstacle2d.json" in cmd
    assert cells.resume_command(tmp_path)[-1] == "--resume=true"
    abl = cells.train_command("cnmp_metaworld_push", "cnmp_noterm", 3, 7, sched, tmp_path / "train")
    assert "--config_path=configs/cnmp_metaworld_push.json" in abl and "--policy.linear_task_term=false" in abl
    assert not any("linear_task_term" in a for a in cells.train_command("cnmp_metaworld_push", "cnmp", 3, 7, sched,
                                                                          tmp_path / "train"))
    ev = cells.eval_command("cnmp_metaworld_reach", "act", ckpt, 50, 10, tmp_path / "eval")
    assert f"--seed={cells.SEED}" in ev and "--eval.n_episodes=50" in ev
    assert any(a.startswith("--rename_map=") for a in ev)
    assert not any(a.startswith("--rename_map=") for a in cells.eval_command("cnmp_metaworld_reach", "cnmp", ckpt,
                                                                               50, 10, tmp_path))
    for task in cells.TASKS.values():
        for config in task["configs"].values():
            assert (cells.REPO / config).is_file(), config


def test_metaworld_configs_are_one_rule_not_tuned_per_task():
    """Every MetaWorld task's config of a method is push's with only the dataset and the job name changed, and
    every task has its recorded dataset."""
    for method, prefix in (("cnmp", "cnmp"), ("act", "act_cpu"), ("diffusion", "diffusion_cpu")):
        ref = json.loads((cells.REPO / f"configs/{prefix}_metaworld_push.json").read_text())
        for task, name in cells.METAWORLD_TASKS.items():
            entry = cells.TASKS[f"cnmp_metaworld_{name}"]
            cfg = json.loads((cells.REPO / entry["configs"][method]).read_text())
            assert cfg["dataset"]["repo_id"].endswith(f"metaworld_{name}" + ("_envstate" if method != "cnmp" else ""))
            assert f"--env.task={task}" in entry["env"]
            assert (cells.REPO / entry["dataset"] / "meta" / "info.json").is_file(), entry["dataset"]
            same = ("dataset", "job_name")
            assert {k: v for k, v in cfg.items() if k not in same} == {k: v for k, v in ref.items() if k not in same}


def test_a_tasks_episode_order(tmp_path):
    """cnmp_pickplace's cells take its grid's corners first; every order is a permutation of the episodes."""
    assert cells.episodes("cnmp_obstacle2d", 3) == [0, 1, 2]
    assert cells.episodes("cnmp_pickplace", 5) == [0, 7, 3, 4, 1]
    for name, task in cells.TASKS.items():
        if "episode_order" in task:
            total = json.loads((cells.REPO / task["dataset"] / "meta" / "info.json").read_text())["total_episodes"]
            assert sorted(task["episode_order"]) == list(range(total)), name


def test_promp_cell_where_it_cannot_condition_is_an_error(tmp_path, monkeypatch):
    bare = {k: v for k, v in cells.TASKS["cnmp_so101"].items() if k != "promp"}  # a task with nothing to condition on
    monkeypatch.setitem(cells.TASKS, "cnmp_so101", bare)
    with pytest.raises(cells.CellError, match="ProMP is not set up"):
        run.run_seed("cnmp_so101", "promp", 5, 0, out=tmp_path, schedule_for=None)


def test_so101_promp_is_contextual_on_the_environment_state():
    assert cells.TASKS["cnmp_so101"]["promp"] == "environment_state"
    assert "--conditioning=environment_state" in cells.fit_command("cnmp_so101", 10, Path("/tmp/x"))


def test_train_loop_time_from_the_log(tmp_path):
    log = tmp_path / "train.log"
    log.write_text("Training:  50%|#####     | 450/900 [00:59<00:59, 7.5step/s]\rTraining: 100%|##########| "
                   "900/900 [02:03<00:00, 7.31step/s]\nINFO End of training\n")
    assert run.train_loop_s(log) == 123.0
    assert run.bar_points(log) == [(450, 59), (900, 123)]
    assert run.seconds_at(run.bar_points(log), 451) == 123.0
    log.write_text("Training:  50%|#####     | 450/900 [00:59<00:59, 7.5step/s]\nTraceback ...\n")
    assert run.train_loop_s(log) is None
    assert run.train_loop_s(tmp_path / "missing.log") is None


def test_methods_without_cells_on_a_task_are_skipped_with_the_reason(tmp_path, monkeypatch, capsys):
    """cnmp_weights has CNMP and ProMP cells only: ACT / Diffusion are skipped (printed, no file, exit 0)."""
    calls = []
    monkeypatch.setattr(cp, "run_seed", lambda task, method, n, seed, **kw: calls.append(method) or
                        {"heldout": {"pc_success": 1.0, "step": 1, "loop_s": 1.0}, "points": []})
    args = ["--tasks", "cnmp_weights", "--methods", "cnmp", "act", "diffusion", "promp", "--demos", "10",
            "--n_seeds", "cnmp=1", "--out", str(tmp_path)]
    assert cp.main(args) == 0
    assert calls == ["cnmp", "promp"]
    assert "validate_features" in capsys.readouterr().out
    with pytest.raises(cells.CellError, match="act has no cell on cnmp_weights"):
        run.run_seed("cnmp_weights", "act", 10, 0, out=tmp_path, schedule_for=None)


def test_camera_cells_are_one_rule_and_see_no_gamma(tmp_path):
    """The camera cells: pick-place's configs are push's with only the dataset and job name changed; every env
    renders the same cameras; no ProMP cell (it conditions on γ); a missing dataset names its record command."""
    same = ("dataset", "job_name")
    push, pick = cells.TASKS["cnmp_metaworld_push_cam"], cells.TASKS["cnmp_metaworld_pickplace_cam"]
    for method in ("cnmp", "act", "diffusion"):
        a, b = (json.loads((cells.REPO / t["configs"][method]).read_text()) for t in (push, pick))
        assert {k: v for k, v in a.items() if k not in same} == {k: v for k, v in b.items() if k not in same}
        assert b["dataset"]["root"] == pick["dataset"]
    cnmp = json.loads((cells.REPO / push["configs"]["cnmp"]).read_text())["policy"]
    assert cnmp["use_images"] is True and "task_features" not in cnmp
    for t in (push, pick):
        assert f"--env.cameras=[{','.join(cells.CAMERAS)}]" in t["env"] and "promp" in t["no_cells"]
        assert "--cameras " + " ".join(cells.CAMERAS) in t["record"]
    with pytest.raises(cells.CellError, match="ProMP is not set up"):
        run.run_seed("cnmp_metaworld_push_cam", "promp", 5, 0, out=tmp_path, schedule_for=None)
    missing = {**push, "dataset": "datasets/absent_cam"}
    with mock.patch.dict(cells.TASKS, {"cnmp_metaworld_push_cam": missing}), \
            pytest.raises(cells.CellError, match="record it with: lerobot-cnmp-record"):
        run.run_seed("cnmp_metaworld_push_cam", "cnmp", 5, 0, out=tmp_path, schedule_for=None)


def test_so101_camera_cell_follows_the_same_rules():
    """SO-101 from one camera: ACT / Diffusion are the MetaWorld camera configs on its dataset; CNMP is the SO-101
    config with the MetaWorld camera cells' image settings (no γ); the env sees the camera and no positions."""
    same = ("dataset", "job_name")
    so101, push = cells.TASKS["cnmp_so101_cam"], cells.TASKS["cnmp_metaworld_push_cam"]
    for method in ("act", "diffusion"):
        a, b = (json.loads((cells.REPO / t["configs"][method]).read_text()) for t in (push, so101))
        assert {k: v for k, v in a.items() if k not in same} == {k: v for k, v in b.items() if k not in same}
        assert b["dataset"]["root"] == so101["dataset"]
    cam, state = (json.loads((cells.REPO / p).read_text()) for p in (so101["configs"]["cnmp"], "configs/cnmp_so101.json"))
    image_keys = ("use_images", "image_encoder")
    assert {k: v for k, v in cam["policy"].items() if k not in image_keys} == state["policy"]
    push_cnmp = json.loads((cells.REPO / push["configs"]["cnmp"]).read_text())["policy"]
    assert {k: cam["policy"][k] for k in image_keys} == {k: push_cnmp[k] for k in image_keys}
    env = cells.env_config("cnmp_so101_cam")
    assert env.cameras == [cells.SO101_CAMERA] and "environment_state" not in env.features
    assert f"--cameras {cells.SO101_CAMERA}" in so101["record"] and "promp" in so101["no_cells"]


def test_env_config_parses_the_eval_arguments_as_lerobot_eval_does():
    """The latency step's EnvConfig comes from the same --env.* arguments, lists and nulls included."""
    cam = cells.env_config("cnmp_metaworld_push_cam")
    assert cam.cameras == cells.CAMERAS and cam.task == "push-v3" and "environment_state" not in cam.features
    assert cells.env_config("cnmp_obstacle2d").render_mode is None

"""CNMPConfig: nested sections from JSON and the command line, the mixture defaults' rule, and the one legacy
upgrade (lerobot_cnmp.policy.legacy) on every committed checkpoint's config.json and on an old flat layout."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import draccus
import pytest
from lerobot.configs import PreTrainedConfig
from lerobot.configs.train import TrainPipelineConfig

from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.policy import legacy
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig, MixtureConfig, SamplingConfig

REPO = Path(__file__).resolve().parents[1]
GOLDEN = sorted(p.parent for p in (REPO / "tests" / "golden").glob("*/config.json"))


def _folder_with_config(dst: Path, config: dict) -> Path:
    dst.mkdir()
    (dst / "config.json").write_text(json.dumps(config))
    return dst


@pytest.mark.parametrize("ckpt", GOLDEN, ids=lambda p: p.name)
def test_every_committed_checkpoint_config_loads_into_the_sections(ckpt):
    """The golden checkpoints written with the flat layout: each flat value lands in its section; those written
    with the sections (after the redesign) load them as written."""
    raw = json.loads((ckpt / "config.json").read_text())
    cfg = PreTrainedConfig.from_pretrained(ckpt)
    assert isinstance(cfg, CNMPConfig)
    if "sampling" in raw:
        assert cfg.sampling == SamplingConfig(**raw["sampling"]) and cfg.mixture == MixtureConfig(**raw["mixture"])
        assert cfg.execution == ExecutionConfig(**raw["execution"])
        return
    for name in legacy.FLAT_SAMPLING:
        assert getattr(cfg.sampling, name) == raw[name], name
    for name in legacy.FLAT_MIXTURE:
        assert getattr(cfg.mixture, name) == raw[name], name
    assert cfg.execution == ExecutionConfig(**raw["execution"])
    assert cfg.n_experts == raw["n_experts"] and list(cfg.decoder_layers) == raw["decoder_layers"]


def test_old_flat_execution_layout_is_taken_as_written():
    """A config from before ``execution`` existed: every flat execution field set, None included; the phase-stop
    semantics it was written for (normalized units, no timeout). A section value given with it wins."""
    old = {"type": "cnmp", "online_feedback": True, "condition_on_start": False, "sigma_scaled_gains": False,
           "numpy_execution": True, "pd_kp": 0.7, "pd_kd": 0.0, "phase_stop_threshold": None, "control_fps": None,
           "n_max_context": 4, "gate_entropy_coef": 0.1, "mixture_nll": "assigned", "gate_commit": "always"}
    up = legacy.upgrade_config_dict(old)
    assert up["execution"] == {"online_feedback": True, "condition_on_start": False, "sigma_scaled_gains": False,
                               "numpy_execution": True, "pd_kp": 0.7, "pd_kd": 0.0, "phase_stop_threshold": None,
                               "control_fps": None, "phase_stop_units": "normalized", "phase_stop_timeout_s": None}
    assert up["sampling"] == {"n_max_context": 4} and up["mixture"] == {"gate_entropy_coef": 0.1}
    assert set(up) == {"type", "execution", "sampling", "mixture"} and "pd_kp" in old  # the input is not changed
    # a partial (newer) config: only the flat values given move, the section's own win
    up = legacy.upgrade_config_dict({"pd_kp": 0.5, "phase_stop_threshold": None, "execution": {"pd_kp": 0.9}})
    assert up == {"execution": {"pd_kp": 0.9}}


def test_old_flat_checkpoint_loads_and_saves_the_new_layout(tmp_path):
    old = json.loads((GOLDEN[0] / "config.json").read_text())
    execution = old.pop("execution")
    old.update({k: execution[k] for k in legacy.FLAT_EXECUTION}, phase_stop_threshold=None, pd_kp=0.7)
    cfg = PreTrainedConfig.from_pretrained(_folder_with_config(tmp_path / "old", old))
    e = cfg.execution
    assert (e.phase_stop_threshold, e.pd_kp, e.phase_stop_units, e.phase_stop_timeout_s) == (None, 0.7, "normalized", None)
    (tmp_path / "new").mkdir()
    cfg._save_pretrained(tmp_path / "new")
    saved = json.loads((tmp_path / "new" / "config.json").read_text())
    assert not set(saved) & (set(legacy.FLAT_EXECUTION) | set(legacy.FLAT_SAMPLING) | set(legacy.FLAT_MIXTURE) | set(legacy.REMOVED))
    again = PreTrainedConfig.from_pretrained(tmp_path / "new")
    assert (again.execution, again.sampling, again.mixture) == (cfg.execution, cfg.sampling, cfg.mixture)


def test_removed_mixture_options_are_dropped_with_a_warning_if_they_mattered(caplog):
    with caplog.at_level(logging.WARNING, logger=legacy.__name__):
        assert legacy.upgrade_config_dict({"mixture_nll": "assigned", "gate_commit": "always"}) == {}
        assert not caplog.records
        assert legacy.upgrade_config_dict({"mixture_nll": "likelihood", "gate_commit": "redundant"}) == {}
    assert "mixture_nll='likelihood'" in caplog.text and "gate_commit='redundant'" in caplog.text


def test_nested_fields_from_the_command_line_and_json(tmp_path):
    cfg = PreTrainedConfig.from_pretrained(GOLDEN[0], cli_overrides=[
        "--mixture.gate_entropy_coef=0.3", "--sampling.n_max_context=6", "--execution.pd_kp=0.5"])
    assert (cfg.mixture.gate_entropy_coef, cfg.sampling.n_max_context, cfg.execution.pd_kp) == (0.3, 6, 0.5)
    assert cfg.pretrained_path is None  # LeRobot's from_pretrained leaves it (lerobot-train/-eval set it)
    train = draccus.parse(TrainPipelineConfig, str(REPO / "configs" / "cnmp_obstacle2d_shared_mix2.json"), args=[
        "--policy.type=cnmp", "--policy.sampling.n_max_context=5", "--policy.mixture.gate_entropy_coef=0.3"])
    p = train.policy
    assert (p.n_experts, p.sampling.n_max_context, p.sampling.draws_per_sample) == (2, 5, 8)
    assert (p.mixture.gate_entropy_coef, p.mixture.expert_selection) == (0.3, "sample")
    # a whole train_config.json of the old flat layout (a run to resume) decodes too
    old = {"policy": {"type": "cnmp", "n_max_context": 3, "pd_kp": 0.5, "mixture_nll": "assigned"},
           "dataset": {"repo_id": "x"}}
    (tmp_path / "train_config.json").write_text(json.dumps(old))
    p = draccus.parse(TrainPipelineConfig, str(tmp_path / "train_config.json"), args=[]).policy
    assert (p.sampling.n_max_context, p.execution.pd_kp) == (3, 0.5)


def test_mixture_defaults_follow_k():
    """None settings: the all-bars setting for K > 1, the neutral one for K = 1 (where another is an error)."""
    one, two = CNMPConfig().mixture, CNMPConfig(n_experts=2).mixture
    assert (one.shared_decoder_layers, one.assignment_draws, one.unconditional_nll_coef) == (0, 0, 1.0)
    assert (two.shared_decoder_layers, two.assignment_draws, two.unconditional_nll_coef) == (3, 1, 0.25)
    assert CNMPConfig(n_experts=2, decoder_layers=(64, 64)).mixture.shared_decoder_layers == 2
    for name, value in (("shared_decoder_layers", 1), ("assignment_draws", 1), ("unconditional_nll_coef", 0.5)):
        with pytest.raises(ValueError, match=f"mixture.{name}={value} applies to a mixture, but n_experts is 1"):
            CNMPConfig(mixture=MixtureConfig(**{name: value}))
    with pytest.raises(ValueError, match="between 0 and the 3 hidden layers"):
        CNMPConfig(n_experts=2, mixture={"shared_decoder_layers": 4})
    assert CNMPConfig(mixture={"gate_entropy_coef": 0.5}).mixture.gate_entropy_coef == 0.5  # unread with K = 1


@pytest.mark.parametrize("kind, field, value", [
    (SamplingConfig, "n_max_context", 0), (SamplingConfig, "draws_per_sample", 1.5),
    (SamplingConfig, "partial_obs_prob", -0.1), (SamplingConfig, "feedback_draw_queries", -1),
    (MixtureConfig, "gate_entropy_coef", float("nan")), (MixtureConfig, "assignment_draws", True),
    (MixtureConfig, "unconditional_nll_coef", float("inf")), (MixtureConfig, "expert_selection", "random"),
])
def test_each_section_checks_its_own_fields(kind, field, value):
    with pytest.raises(ValueError, match=field):
        kind(**{field: value})


def test_at_most_30_fields_and_no_flat_alias_left():
    own = {f for f in CNMPConfig.__dataclass_fields__} - set(PreTrainedConfig.__dataclass_fields__)
    assert len(own) <= 30
    assert not own & (set(legacy.FLAT_EXECUTION) | set(legacy.FLAT_SAMPLING) | set(legacy.FLAT_MIXTURE) | set(legacy.REMOVED))

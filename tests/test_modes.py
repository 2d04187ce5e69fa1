"""The mode rule of a mixture CNMP's execution (lerobot_cnmp.execution.modes), on its own."""

import pytest
import torch

from lerobot_cnmp.execution.modes import ModeSelector


def test_first_step_takes_the_most_probable_expert_and_keeps_it_within_the_margin():
    sel = ModeSelector(margin=0.3)
    assert sel(torch.tensor([[0.2, 0.5, 0.3], [0.6, 0.3, 0.1]])).tolist() == [1, 0]
    # another expert ahead, but by no more than the margin: keep
    assert sel(torch.tensor([[0.1, 0.35, 0.55], [0.35, 0.6, 0.05]])).tolist() == [1, 0]
    # clearly ahead (lead 0.5 > 0.3) in env 0 only: env 0 switches, env 1 keeps
    assert sel(torch.tensor([[0.05, 0.2, 0.75], [0.4, 0.5, 0.1]])).tolist() == [2, 0]
    assert sel.switches.tolist() == [1, 0]
    # after a switch the new expert is kept under the same rule
    assert sel(torch.tensor([[0.1, 0.45, 0.45], [0.4, 0.5, 0.1]])).tolist() == [2, 0]


def test_reset_and_a_new_batch_start_over():
    sel = ModeSelector(margin=0.3)
    sel(torch.tensor([[0.9, 0.1]]))
    assert sel(torch.tensor([[0.45, 0.55]])).tolist() == [0]
    sel.reset()
    assert sel(torch.tensor([[0.45, 0.55]])).tolist() == [1]  # a first step again
    assert sel(torch.tensor([[0.9, 0.1], [0.2, 0.8]])).tolist() == [0, 1]  # another number of envs


def test_zero_margin_always_follows_the_gate():
    sel = ModeSelector(margin=0.0)
    sel(torch.tensor([[0.6, 0.4]]))
    assert sel(torch.tensor([[0.49, 0.51]])).tolist() == [1]


def test_sampled_first_choice_follows_the_gate():
    gen = torch.Generator().manual_seed(0)
    sel = ModeSelector(margin=0.3, selection="sample", generator=gen)
    picks = sel(torch.tensor([[0.5, 0.5, 0.0]]).expand(4000, -1))
    counts = torch.bincount(picks, minlength=3)
    assert counts[2] == 0 and 1800 < counts[0] < 2200  # ~ half each, never the impossible expert
    # later steps follow the margin rule, not a new draw
    assert torch.equal(sel(torch.tensor([[0.4, 0.6, 0.0]]).expand(4000, -1)), picks)


@pytest.mark.parametrize("kw, match", [({"margin": 1.0}, "margin"), ({"margin": -0.1}, "margin"),
                                       ({"selection": "best"}, "selection")])
def test_bad_settings(kw, match):
    with pytest.raises(ValueError, match=match):
        ModeSelector(**kw)


def test_bad_probabilities():
    sel = ModeSelector()
    with pytest.raises(ValueError, match="envs, experts"):
        sel(torch.tensor([0.5, 0.5]))
    with pytest.raises(ValueError, match="finite"):
        sel(torch.tensor([[float("nan"), 0.5]]))

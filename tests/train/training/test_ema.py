"""The weight average: its update rule, its frozen copy, and its stress cases."""

import pytest
import torch

from train.training.ema import averaged_copy, update_average


def _net():
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    with torch.no_grad():
        net[1].weight.copy_(torch.tensor([0.1, 0.3, 0.7, 1.9]))  # x d + x (1 - d) != x in float for these
    net[1].weight.requires_grad_(False)  # a frozen weight is copied, never averaged
    return net


def test_average_is_a_frozen_copy_that_leaves_the_module_alone():
    net = _net()
    avg = averaged_copy(net)
    assert not any(p.requires_grad for p in avg.parameters())
    assert net[0].weight.requires_grad and all(torch.equal(a, b) for a, b in zip(avg.parameters(), net.parameters()))
    with torch.no_grad():
        net[0].weight.add_(1.0)
    assert not torch.equal(avg[0].weight, net[0].weight)  # a copy, not a view


@pytest.mark.parametrize("decay", [0.0, 0.5, 0.9, 0.97])
def test_update_follows_the_closed_form_and_copies_buffers(decay):
    net = _net()
    avg = averaged_copy(net)
    a0 = avg[0].weight.clone()
    with torch.no_grad():
        net[0].weight.fill_(2.0)  # the live weight jumps once and stays
        net[1].running_mean.fill_(3.0)
    for _ in range(5):
        update_average(avg, net, decay)
    expect = 2.0 + (a0 - 2.0) * decay**5
    torch.testing.assert_close(avg[0].weight, expect)
    assert torch.equal(avg[1].running_mean, net[1].running_mean)
    with torch.no_grad():
        net[1].weight.mul_(3.0)  # a frozen weight changed by hand: the average takes it bit for bit
    update_average(avg, net, decay)
    assert torch.equal(avg[1].weight, net[1].weight)


def test_average_of_a_moving_weight_lags_it():
    net = _net()
    avg = averaged_copy(net)
    for k in range(1, 21):
        with torch.no_grad():
            net[0].bias.fill_(float(k))
        update_average(avg, net, 0.8)
    # A ramp of slope 1 seen through an average of horizon 1 / (1 - d): behind by about d / (1 - d) = 4.
    assert 15.5 < float(avg[0].bias.mean()) < 16.5


def test_extreme_weights_stay_finite():
    net = _net()
    avg = averaged_copy(net)
    with torch.no_grad():
        net[0].weight.fill_(3e38)
        avg[0].weight.fill_(-3e38)
    update_average(avg, net, 0.999)
    assert torch.isfinite(avg[0].weight).all()

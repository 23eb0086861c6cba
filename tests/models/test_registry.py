"""The model registry, every registered network's outputs, size and FLOP count."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from evtrack.errors import ConfigError
from evtrack.models import (
    count_flops,
    count_parameters,
    create,
    is_model,
    list_models,
    register_model,
)

MAX_PARAMETERS = 5_000_000


def test_registry_lists_the_family():
    names = list_models()
    assert {"dope_lite_tiny", "dope_lite_small", "dope_lite_base", "dope_lite_large"} <= set(names)
    assert list_models("*tiny") == ["dope_lite_tiny"]
    assert is_model("dope_lite_base") and not is_model("vgg19")


@pytest.mark.parametrize("name", list_models())
def test_every_model_outputs_dope_maps_at_stride_8(name):
    torch.manual_seed(0)
    net = create(name).eval()
    assert net.arch_name == name and net.weights_record is None
    assert count_parameters(net) <= MAX_PARAMETERS
    x = torch.randn(2, 3, 64, 96)
    with torch.no_grad():
        belief, affinity = net(x)
        stages = net.forward_stages(x)
    assert belief.shape == (2, 9, 8, 12) and affinity.shape == (2, 16, 8, 12)
    assert len(stages) == net.num_stages
    torch.testing.assert_close(stages[-1][0], belief)
    # odd multiples of 8 (not of 32) work too: the top-down path resizes to the skip size
    with torch.no_grad():
        b, a = net(torch.randn(1, 3, 40, 56))
    assert b.shape == (1, 9, 5, 7) and a.shape == (1, 16, 5, 7)


def test_flop_counter_matches_a_hand_count_on_a_convolution():
    conv = nn.Conv2d(3, 5, 3, stride=2, padding=1, bias=False)
    # 2 FLOPs per multiply-accumulate, one output (5 x 8 x 12) each over 3 x 3 x 3 inputs
    assert count_flops(conv, 16, 24) == 2 * 5 * 8 * 12 * 3 * 3 * 3


def test_network_flops_grow_with_the_pixel_count():
    net = create("dope_lite_tiny")
    small, big = count_flops(net, 64, 96), count_flops(net, 128, 192)
    assert small > 0
    assert big == pytest.approx(4 * small, rel=0.02)


def test_kwargs_override_hyper_parameters():
    net = create("dope_lite_tiny", num_stages=2)
    assert net.num_stages == 2 and net.arch_kwargs == {"num_stages": 2}


def test_bad_names_and_hyper_parameters_are_config_errors():
    with pytest.raises(ConfigError, match="unknown model 'nope'"):
        create("nope")
    with pytest.raises(ConfigError, match="unknown DOPE-Lite hyper-parameter"):
        create("dope_lite_tiny", widht=3)
    with pytest.raises(ConfigError, match="num_stages"):
        create("dope_lite_tiny", num_stages=0)


def test_registering_a_name_twice_fails():
    with pytest.raises(ValueError, match="already registered"):

        @register_model
        def dope_lite_tiny(**kwargs):  # noqa: F811
            return nn.Identity()

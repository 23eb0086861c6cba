"""twist_agreement: gains and errors of estimated twists against the truth."""

import math

import pytest
import torch

from evtrack.eval.twist_metrics import scale_gain, twist_agreement


def _random_twists(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    twists = torch.randn(n, 6, generator=g, dtype=torch.float64)
    twists[:, :3] *= 0.3
    twists[:, 3:] *= 2.0
    centres = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.1
    centres[:, 2] = 0.4 + torch.rand(n, generator=g, dtype=torch.float64)
    return twists, centres


def _skew(w: torch.Tensor) -> torch.Tensor:
    return torch.tensor([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]],
                        dtype=torch.float64)


def test_a_scaled_estimate_has_that_gain_in_every_part():
    truth, centres = _random_twists(50, 0)
    agreement = twist_agreement(0.6 * truth, truth, centres)
    for name in ("gain_linear", "gain_angular", "gain_centre", "gain_centre_image",
                 "gain_centre_depth", "gain_along_sight", "gain_across_sight"):
        assert getattr(agreement, name) == pytest.approx(0.6, abs=1e-12), name
    assert agreement.samples == 50
    assert agreement.rmse_angular_rad_s == pytest.approx(
        0.4 * float((truth[:, 3:] ** 2).sum(1).mean().sqrt()), rel=1e-12)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_zero_mean_noise_leaves_the_gain_near_one(seed):
    truth, centres = _random_twists(20000, seed)
    g = torch.Generator().manual_seed(100 + seed)
    noisy = truth + torch.randn(truth.shape, generator=g, dtype=torch.float64) * 1.0
    agreement = twist_agreement(noisy, truth, centres)
    assert agreement.gain_angular == pytest.approx(1.0, abs=0.02)
    assert agreement.gain_linear == pytest.approx(1.0, abs=0.05)
    assert agreement.rmse_angular_rad_s == pytest.approx(math.sqrt(3.0), rel=0.03)


def test_the_centre_velocity_is_the_finite_difference_of_the_moving_centre():
    """v_c against the centre moved by the SE(3) exponential of the twist (central difference):
    an estimate with that centre velocity and no rotation has centre gain 1, angular gain 0."""
    truth, centres = _random_twists(8, 4)
    h = 1e-6
    moved = []
    for twist, c in zip(truth, centres, strict=True):
        xi = torch.zeros(4, 4, dtype=torch.float64)
        xi[:3, :3] = _skew(twist[3:])
        xi[:3, 3] = twist[:3]
        point = torch.cat([c, torch.ones(1, dtype=torch.float64)])
        ahead = torch.linalg.matrix_exp(h * xi) @ point
        behind = torch.linalg.matrix_exp(-h * xi) @ point
        moved.append((ahead[:3] - behind[:3]) / (2 * h))
    centre_velocity = torch.stack(moved)
    translation_only = torch.cat([centre_velocity, torch.zeros(8, 3, dtype=torch.float64)], 1)
    agreement = twist_agreement(translation_only, truth, centres)
    assert agreement.gain_centre == pytest.approx(1.0, abs=1e-6)
    assert agreement.rmse_centre_m_s == pytest.approx(0.0, abs=1e-6)
    assert agreement.gain_angular == 0.0


def test_rotation_split_along_and_across_the_line_of_sight():
    truth, centres = _random_twists(30, 5)
    sight = centres / centres.norm(dim=1, keepdim=True)
    along = (truth[:, 3:] * sight).sum(1, keepdim=True) * sight
    only_along = torch.cat([truth[:, :3], along], 1)
    agreement = twist_agreement(only_along, truth, centres)
    assert agreement.gain_along_sight == pytest.approx(1.0, abs=1e-12)
    assert agreement.gain_across_sight == pytest.approx(0.0, abs=1e-12)
    assert 0.0 < agreement.gain_angular < 1.0


def test_rows_with_a_nan_are_left_out_and_counted():
    truth, centres = _random_twists(10, 6)
    estimate = 0.5 * truth
    estimate[2, 4] = float("nan")
    centres[7, 0] = float("inf")
    agreement = twist_agreement(estimate, truth, centres)
    assert agreement.samples == 8
    assert agreement.gain_angular == pytest.approx(0.5, abs=1e-12)
    empty = twist_agreement(torch.full((3, 6), float("nan")), truth[:3], centres[:3])
    assert empty.samples == 0 and math.isnan(empty.gain_angular)
    assert math.isnan(empty.rmse_angular_rad_s)


def test_shapes_that_do_not_match_are_refused():
    truth, centres = _random_twists(4, 7)
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        twist_agreement(truth[:3], truth, centres)
    with pytest.raises(ValueError, match="centres"):
        twist_agreement(truth, truth, centres[:, :2])


def test_scale_gain_of_a_zero_truth_is_nan():
    assert math.isnan(scale_gain(torch.ones(3), torch.zeros(3)))
    assert scale_gain(torch.tensor([2.0, 4.0]), torch.tensor([1.0, 2.0])) == pytest.approx(2.0)

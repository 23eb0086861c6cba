"""PinholeCamera against OpenCV (an independent implementation of the same model)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from evtrack import ConfigError, PinholeCamera

DIST = [-0.21, 0.07, 0.0013, -0.0009, -0.012]


def random_points(n: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 0.8
    z = 0.4 + torch.rand(n, 1, generator=g, dtype=torch.float64)
    return torch.cat([xy * z, z], dim=1)


@pytest.mark.parametrize("dist", [None, DIST])
def test_project_matches_opencv(dist):
    cam = PinholeCamera(610.0, 605.0, 331.5, 236.0, 640, 480, dist=dist)
    P = random_points()
    uv = cam.project(P)
    ref, _ = cv2.projectPoints(P.numpy(), np.zeros(3), np.zeros(3), cam.K().numpy(),
                               None if dist is None else np.array(dist))
    assert np.allclose(uv.numpy(), ref.reshape(-1, 2), atol=1e-6)


def test_undistort_matches_opencv():
    cam = PinholeCamera(610.0, 605.0, 331.5, 236.0, 640, 480, dist=DIST)
    uv = cam.project(random_points(seed=1))
    ours = cam.undistort_points(uv)
    ref = cv2.undistortPoints(
        uv.numpy().reshape(-1, 1, 2), cam.K().numpy(), np.array(DIST), None, cam.K().numpy(),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
    ).reshape(-1, 2)
    assert np.allclose(ours.numpy(), ref, atol=1e-4)


@pytest.mark.parametrize("dist", [None, DIST])
def test_unproject_inverts_project(dist):
    cam = PinholeCamera(500.0, 520.0, 300.0, 250.0, 640, 480, dist=dist)
    P = random_points(seed=2)
    back = cam.unproject(cam.project(P), P[:, 2])
    assert torch.allclose(back, P, atol=1e-6)


def test_principal_point_projects_to_centre():
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    assert cam.project(torch.tensor([[0.0, 0.0, 2.0]])).tolist() == [[320.0, 240.0]]


def test_batched_shapes():
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, dist=DIST)
    P = random_points(24).reshape(2, 3, 4, 3)
    assert cam.project(P).shape == (2, 3, 4, 2)
    assert cam.unproject(cam.project(P), P[..., 2]).shape == (2, 3, 4, 3)


def test_yaml_roundtrip(tmp_path):
    cam = PinholeCamera(500.0, 501.0, 320.5, 240.5, 640, 480, dist=DIST)
    cam.to_yaml(tmp_path / "cam.yaml")
    assert PinholeCamera.from_yaml(tmp_path / "cam.yaml") == cam
    plain = PinholeCamera(1.0, 1.0, 0.0, 0.0, 2, 2)
    plain.to_yaml(tmp_path / "plain.yaml")
    assert PinholeCamera.from_yaml(tmp_path / "plain.yaml").dist is None


def test_yaml_missing_field_names_file_and_field(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("fx: 500\nfy: 500\ncx: 1\nwidth: 2\nheight: 2\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*'cy'"):
        PinholeCamera.from_yaml(path)


def test_invalid_values():
    with pytest.raises(ConfigError, match="focal"):
        PinholeCamera(-1.0, 1.0, 0, 0, 2, 2)
    with pytest.raises(ConfigError, match="coefficients"):
        PinholeCamera(1.0, 1.0, 0, 0, 2, 2, dist=[0.1, 0.2, 0.3])
    with pytest.raises(ConfigError, match="unknown"):
        PinholeCamera.from_dict({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 2, "height": 2,
                                 "fz": 3})


def test_fields_of_the_wrong_type_are_named():
    good = {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 2, "height": 2}
    with pytest.raises(ConfigError, match="camera field 'fx' must be a number, got 'abc'"):
        PinholeCamera.from_dict({**good, "fx": "abc"})
    with pytest.raises(ConfigError, match="'width' must be a whole number of pixels, got 320.5"):
        PinholeCamera.from_dict({**good, "width": 320.5})  # once truncated to 320
    assert PinholeCamera.from_dict({**good, "width": 2.0}).width == 2


def test_scaled_keeps_pixel_centres():
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    half = cam.scaled(0.5)
    P = random_points(seed=3)
    # a point at pixel-centre coordinate u maps to (u + 0.5) * s - 0.5
    assert torch.allclose(half.project(P), (cam.project(P) + 0.5) * 0.5 - 0.5, atol=1e-9)

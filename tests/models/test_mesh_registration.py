"""Global registration (evtrack.models.mesh_registration): a pose found on one RGB-D frame from
the textured mesh alone, given a box around the object."""

from __future__ import annotations

import numpy as np
import pytest
from test_appearance_refine import BOX_POSE, CAM, CAN_POSE, angle_deg, frame_of

from evtrack.errors import ConfigError
from evtrack.models.mesh_registration import RegistrationConfig, register_mesh
from evtrack.sim.objects import procedural_object


def scene(mesh, T, wall_m: float = 1.2):
    """The RGB frame, a perfect depth frame (a wall behind the object) and a box 5 px around
    the object's silhouette."""
    from evtrack.sim.renderer import Renderer

    with Renderer(CAM) as r:
        r.set_object(mesh)
        out = r.render(T)
    depth = np.where(out.mask, out.depth, wall_m).astype(np.float32)
    vs, us = np.nonzero(out.mask)
    box = (int(us.min()) - 5, int(vs.min()) - 5, int(us.max()) + 6, int(vs.max()) + 6)
    return frame_of(mesh, T), depth, box


@pytest.mark.parametrize(("kind", "truth"), [("can", CAN_POSE), ("box", BOX_POSE)])
def test_the_pose_is_found_from_the_mesh_alone(gl, kind, truth) -> None:
    """Depth orients the shape; the texture picks the can's spin about its axis, which the
    depth cannot see: within 1° and 3 mm, the colour image confirming it."""
    mesh = procedural_object(kind, 3)
    rgb, depth, box = scene(mesh, truth)
    found = register_mesh(mesh, CAM, rgb, depth, box, RegistrationConfig(rotations=48))
    assert angle_deg(found.pose, truth) < 1.0
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.003
    assert found.correlation > 0.95
    assert found.tried == 48 and 0 < found.fitted <= 48
    if found.runner_up is not None:  # another orientation: farther, and worse
        assert found.runner_up[1] > 20.0 and found.runner_up[0] < found.correlation


def test_what_it_refuses(gl) -> None:
    mesh = procedural_object("box", 3)
    rgb, depth, box = scene(mesh, BOX_POSE)
    fast = RegistrationConfig(rotations=12, candidates=4)
    with pytest.raises(ValueError, match="holds no part"):
        register_mesh(mesh, CAM, rgb, depth, (400, 300, 500, 400), fast)
    with pytest.raises(ValueError, match="valid depth pixels inside the box"):
        register_mesh(mesh, CAM, rgb, np.zeros_like(depth), box, fast)
    with pytest.raises(ValueError, match=r"depth must be \(240, 320\)"):
        register_mesh(mesh, CAM, rgb, depth[:100], box, fast)
    blank = np.full_like(rgb, 80)  # the colour image shows nothing of the object
    with pytest.raises(ValueError, match="confirms none"):
        register_mesh(mesh, CAM, blank, depth, box, fast)
    with pytest.raises(ConfigError, match="rotations and candidates"):
        RegistrationConfig(rotations=0)

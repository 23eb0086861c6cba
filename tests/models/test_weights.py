"""Weights files: records, safe loading, wrong architecture/object/hyper-parameters, the zoo."""

from __future__ import annotations

import pytest
import torch

import evtrack.models.weights as weights_module
from evtrack.errors import ConfigError
from evtrack.models import (
    Cuboid,
    WeightsError,
    WeightsRecord,
    create,
    find_default_weights,
    list_weights,
    load_model,
    load_weights_file,
    model_card,
    save_weights,
)


def make_record(arch="dope_lite_tiny", obj="demo_box", **kw) -> WeightsRecord:
    return WeightsRecord(arch=arch, object_name=obj, cuboid=Cuboid((0.1, 0.2, 0.05), (0, 0.01, 0)),
                         input_size=(96, 128), training_data="unit test", **kw)


@pytest.fixture()
def saved(tmp_path):
    torch.manual_seed(3)
    net = create("dope_lite_tiny")
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn_like(p))
    path = save_weights(tmp_path / "w.pt", net, make_record(metrics={"val/loss": 0.5}))
    return net, path


def test_roundtrip_restores_state_and_record(saved):
    net, path = saved
    loaded = create("dope_lite_tiny", weights=path)
    assert not loaded.training
    for k, v in net.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v)
    rec = loaded.weights_record
    assert rec == make_record(metrics={"val/loss": 0.5}, created=rec.created)
    assert rec.cuboid == Cuboid((0.1, 0.2, 0.05), (0, 0.01, 0))
    net2, rec2 = load_model(path)
    assert net2.arch_name == "dope_lite_tiny" and rec2.object_name == "demo_box"


def test_file_is_plain_data_for_weights_only_loading(saved):
    _, path = saved
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == "evtrack.pose_weights"
    assert payload["record"]["arch"] == "dope_lite_tiny"


def test_wrong_architecture_is_a_clear_error(saved):
    _, path = saved
    with pytest.raises(WeightsError, match="architecture 'dope_lite_tiny', not 'dope_lite_small'"):
        create("dope_lite_small", weights=path)


def test_wrong_object_is_a_clear_error(saved):
    _, path = saved
    with pytest.raises(WeightsError, match="object 'demo_box', not 'mustard'"):
        create("dope_lite_tiny", weights=path, object_name="mustard")
    with pytest.raises(WeightsError, match="object"):
        load_model(path, object_name="mustard")


def test_conflicting_hyper_parameters_are_refused(saved):
    _, path = saved
    with pytest.raises(WeightsError, match="differ from those of the weights"):
        create("dope_lite_tiny", weights=path, refine_dilations=[1, 3])


def test_record_lying_about_the_architecture_is_caught(tmp_path):
    small = create("dope_lite_small")
    path = save_weights(tmp_path / "lie.pt", small, make_record(arch="dope_lite_tiny"))
    with pytest.raises(WeightsError, match="do not fit dope_lite_tiny"):
        create("dope_lite_tiny", weights=path)


def test_pickled_code_is_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": "evtrack.pose_weights", "obj": torch.nn.Linear(2, 2)}, path)
    with pytest.raises(WeightsError, match="weights_only=True"):
        load_weights_file(path)


@pytest.mark.parametrize(("content", "says"), [
    (b"", "neither a torch.save zip archive nor a pickle"),
    (b"not a zip file at all", "neither a torch.save zip archive nor a pickle"),
    (b"\x89HDF\r\n\x1a\n" + bytes(100), "this is an HDF5 file, not a .pt weights file"),
    (b"\x08\x08\x12\x07pytorch", "this is an ONNX model, not a .pt weights file"),
    (b"PK\x03\x04 a cut zip", "cannot read weights"),
])
def test_corrupt_or_foreign_files_are_clear_errors(tmp_path, content, says):
    path = tmp_path / "bad.pt"
    path.write_bytes(content)
    with pytest.raises(WeightsError, match=says):
        load_weights_file(path)


def test_truncated_file_is_a_clear_error(saved, tmp_path):
    _, path = saved
    cut = tmp_path / "cut.pt"
    cut.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(WeightsError, match=str(cut)):
        load_weights_file(cut)


def test_foreign_and_missing_files(tmp_path):
    other = tmp_path / "other.pt"
    torch.save({"model": {"w": torch.zeros(1)}}, other)
    with pytest.raises(WeightsError, match="not an evtrack weights file"):
        load_weights_file(other)
    with pytest.raises(WeightsError, match="not found"):
        create("dope_lite_tiny", weights=tmp_path / "missing.pt")
    bad_version = tmp_path / "v9.pt"
    torch.save({"format": "evtrack.pose_weights", "format_version": 9}, bad_version)
    with pytest.raises(WeightsError, match="version 9"):
        load_weights_file(bad_version)


def test_lightning_style_checkpoint_is_accepted(saved, tmp_path):
    net, path = saved
    payload = torch.load(path, weights_only=True)
    ckpt = {
        "state_dict": {f"net.{k}": v for k, v in payload["state_dict"].items()},
        "hyper_parameters": {"record": payload["record"], "optim": {"lr": 1e-3}},
        "epoch": 3,
    }
    torch.save(ckpt, tmp_path / "x.ckpt")
    loaded = create("dope_lite_tiny", weights=tmp_path / "x.ckpt")
    torch.testing.assert_close(loaded.state_dict(), net.state_dict())
    torch.save({"state_dict": {}, "hyper_parameters": {}}, tmp_path / "y.ckpt")
    with pytest.raises(WeightsError, match="without an evtrack weights record"):
        load_weights_file(tmp_path / "y.ckpt")


def test_default_weights_come_from_the_zoo(saved, tmp_path, monkeypatch):
    net, path = saved
    zoo = tmp_path / "zoo"
    zoo.mkdir()
    monkeypatch.setattr(weights_module, "zoo_dir", lambda: zoo)
    with pytest.raises(WeightsError, match="no shipped weights for dope_lite_tiny"):
        create("dope_lite_tiny", weights="default")
    (zoo / "demo.pt").write_bytes(path.read_bytes())
    assert [r.object_name for _, r in list_weights()] == ["demo_box"]
    loaded = create("dope_lite_tiny", weights="default")
    torch.testing.assert_close(loaded.state_dict(), net.state_dict())
    save_weights(zoo / "other.pt", net, make_record(obj="other_box"))
    with pytest.raises(WeightsError, match="several weights"):
        find_default_weights("dope_lite_tiny")
    assert find_default_weights("dope_lite_tiny", "other_box").name == "other.pt"


def test_model_card_states_what_the_weights_are():
    card = model_card(make_record(metrics={"val/loss": 0.25}, training={"wall_time_s": 12.5}),
                      config={"model": {"name": "dope_lite_tiny"}})
    for text in ("dope_lite_tiny", "demo_box", "unit test", "BSD-3-Clause", "val/loss: 0.25",
                 "wall_time_s: 12.5", "trained at 128x96", "```yaml"):
        assert text in card


def test_record_validation():
    with pytest.raises(WeightsError, match="lacks field"):
        WeightsRecord.from_dict({"arch": "x"})
    with pytest.raises(WeightsError, match="unknown field"):
        WeightsRecord.from_dict({**make_record().to_dict(), "colour": "red"})
    assert WeightsRecord.from_dict(make_record().to_dict()) == make_record(
        created=WeightsRecord.from_dict(make_record().to_dict()).created)


def test_the_records_decoding_is_used_unless_one_is_given(saved, tmp_path):
    """``WeightsRecord.decode``: saved with the weights, applied by estimators built from them
    (the library's defaults elsewhere), overridden by an explicit ``decode``, checked by
    field name."""
    from evtrack.models import DecodeConfig, TorchPoseEstimator
    from evtrack.models.factory import load_model

    net, _ = saved
    chosen = {"crop_blend_max_deg": 45.0, "search_below": 0.2}
    path = save_weights(tmp_path / "chosen.pt", net, make_record(decode=chosen))
    record, state = load_weights_file(path)
    assert record.decode == chosen
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())
    cam = torch.tensor([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]]).numpy()
    est = TorchPoseEstimator.from_weights(path, cam)
    assert est.decode == DecodeConfig(crop_blend_max_deg=45.0, search_below=0.2)
    explicit = TorchPoseEstimator.from_weights(path, cam, decode=DecodeConfig())
    assert explicit.decode == DecodeConfig()
    plain_net, plain_record = load_model(saved[1])
    assert plain_record.decode == {}
    assert TorchPoseEstimator(plain_net, cam).decode == DecodeConfig()
    with pytest.raises(ConfigError, match=r"record\.decode.*crop_blend"):
        make_record(decode={"crop_blend": 45.0})
    with pytest.raises(ConfigError, match="crop_blend_max_deg"):
        make_record(decode={"crop_blend_max_deg": 200.0})
    with pytest.raises(WeightsError, match="decode"):
        WeightsRecord.from_dict({**make_record().to_dict(), "decode": ["crop_blend_max_deg"]})


def test_set_decode_command_writes_the_records_decoding(saved, tmp_path, capsys):
    """``evtrack set-decode``: sets, shows and clears ``WeightsRecord.decode``; the state dict
    is copied as it is; bad names and values are errors that name the field and write nothing."""
    from evtrack.cli import main

    net, path = saved
    out = tmp_path / "decoded.pt"
    assert main(["set-decode", str(path), "crop_blend_max_deg=45", "ransac=false",
                 "--out", str(out)]) == 0
    record, state = load_weights_file(out)
    assert record.decode == {"crop_blend_max_deg": 45, "ransac": False}
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())
    assert load_weights_file(path)[0].decode == {}  # the input is untouched with --out
    assert main(["set-decode", str(out)]) == 0
    assert "crop_blend_max_deg" in capsys.readouterr().out
    assert main(["set-decode", str(out), "search_below=0.2"]) == 0  # in place, merged
    assert load_weights_file(out)[0].decode == {"crop_blend_max_deg": 45, "ransac": False,
                                                 "search_below": 0.2}
    assert main(["set-decode", str(out), "--clear"]) == 0
    assert load_weights_file(out)[0].decode == {}
    for bad, field_name in (("crop_blend=45", "crop_blend"), ("ransac=maybe", "ransac"),
                            ("crop_blend_max_deg=abc", "crop_blend_max_deg"),
                            ("crop_blend_max_deg=500", "crop_blend_max_deg"), ("45", "KEY=VALUE"),
                            # once stored, then a ZeroDivisionError or no pose while tracking
                            ("reprojection_scale_px=0", "reprojection_scale_px"),
                            ("peak_threshold=.nan", "peak_threshold"),
                            ("peak_threshold=2", "peak_threshold"),
                            ("ransac_iterations=0", "ransac_iterations"),
                            ("ransac_reprojection_px=-1", "ransac_reprojection_px"),
                            ("min_affinity_norm=-3", "min_affinity_norm")):
        target = tmp_path / "never.pt"
        assert main(["set-decode", str(path), bad, "--out", str(target)]) == 1
        assert field_name in capsys.readouterr().err and not target.exists()


def test_decode_config_from_dict_checks_value_types():
    from evtrack.models import DecodeConfig

    assert DecodeConfig.from_dict({"crop_blend_max_deg": 45}).crop_blend_max_deg == 45.0
    assert isinstance(DecodeConfig.from_dict({"search_below": 0}).search_below, float)
    for bad in ({"ransac": 1}, {"min_points": 5.5}, {"min_points": True},
                {"correspondence": 3}, {"search_below": "0.1"}):
        with pytest.raises(ConfigError, match=f"^decode: {next(iter(bad))}: (expected|must be) "):
            DecodeConfig.from_dict(bad)

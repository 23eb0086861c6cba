"""Averaging weights files: the mean tensor by tensor, the record, and what is refused."""

from __future__ import annotations

import pytest
import torch

from evtrack.cli import main
from evtrack.errors import ConfigError
from evtrack.models import (
    Cuboid,
    WeightsError,
    WeightsRecord,
    average_weights,
    create,
    load_model,
    save_weights,
)

CUBOID = Cuboid((0.1, 0.16, 0.07))


def _weights(path, seed, object_name="box", steps=10):
    torch.manual_seed(seed)
    net = create("dope_lite_tiny")
    with torch.no_grad():  # batch-norm statistics that differ between the files too
        for name, buf in net.named_buffers():
            if name.endswith("running_mean"):
                buf.normal_()
            elif name.endswith("num_batches_tracked"):
                buf.fill_(steps)
    record = WeightsRecord(arch="dope_lite_tiny", object_name=object_name, cuboid=CUBOID,
                           origin=f"run {seed}", metrics={"val/loss": 0.1},
                           training={"steps": steps}, training_data=f"renders seed {seed}")
    return save_weights(path, net, record), net.state_dict()


def test_the_mean_is_taken_tensor_by_tensor_with_optional_factors(tmp_path):
    a, sa = _weights(tmp_path / "a.pt", 0, steps=10)
    b, sb = _weights(tmp_path / "b.pt", 1, steps=30)
    for factors, wa in ((None, 0.5), ([3.0, 1.0], 0.75)):
        out = average_weights([a, b], tmp_path / "mean.pt", factors)
        net, record = load_model(out)
        state = net.state_dict()
        for key, value in sa.items():
            if value.is_floating_point():
                torch.testing.assert_close(state[key], wa * value + (1 - wa) * sb[key])
            else:  # num_batches_tracked: the largest
                assert int(state[key]) == 30
        assert record.metrics == {}  # measured on neither: not carried over
        assert [r["factor"] for r in record.training["averaged"]] == [wa, 1 - wa]
        assert [r["steps"] for r in record.training["averaged"]] == [10, 30]
        assert str(a) in record.origin and str(b) in record.origin
        assert record.training_data == "renders seed 0 | renders seed 1"
    # the mean of a file with itself is that file
    same = load_model(average_weights([a, a], tmp_path / "same.pt"))[0].state_dict()
    torch.testing.assert_close(same, sa)


def test_weights_of_other_networks_or_bad_factors_are_refused(tmp_path):
    a, _ = _weights(tmp_path / "a.pt", 0)
    mug, _ = _weights(tmp_path / "mug.pt", 1, object_name="mug")
    with pytest.raises(WeightsError, match=r"mug\.pt: record field 'object_name' is 'mug'"):
        average_weights([a, mug], tmp_path / "out.pt")
    small = create("dope_lite_small")
    other = save_weights(tmp_path / "small.pt", small, WeightsRecord(
        arch="dope_lite_small", object_name="box", cuboid=CUBOID))
    with pytest.raises(WeightsError, match="'arch' is 'dope_lite_small'"):
        average_weights([a, other], tmp_path / "out.pt")
    with pytest.raises(WeightsError, match="at least two"):
        average_weights([a], tmp_path / "out.pt")
    with pytest.raises(WeightsError, match="not found"):
        average_weights([a, tmp_path / "none.pt"], tmp_path / "out.pt")
    with pytest.raises(ConfigError, match="positive sum"):
        average_weights([a, a], tmp_path / "out.pt", [1.0, -1.0])
    with pytest.raises(ConfigError, match="the output is one of the inputs"):
        average_weights([a, a], a)
    for bad in (float("nan"), float("inf")):  # both once wrote all-NaN weights
        with pytest.raises(ConfigError, match="finite"):
            average_weights([a, a], tmp_path / "out.pt", [bad, 1.0])
    with pytest.raises(ConfigError, match="3 factors for 2"):
        average_weights([a, a], tmp_path / "out.pt", [1.0, 1.0, 1.0])
    assert not (tmp_path / "out.pt").exists()  # nothing written on a refusal


def test_average_weights_command(tmp_path, capsys):
    a, _ = _weights(tmp_path / "a.pt", 0)
    b, _ = _weights(tmp_path / "b.pt", 1)
    out = tmp_path / "soup" / "mean.pt"
    assert main(["average-weights", str(a), str(b), "--out", str(out)]) == 0
    assert "wrote the mean of 2 weights files" in capsys.readouterr().out
    assert load_model(out)[1].object_name == "box"
    assert str(a) in out.with_suffix(".md").read_text()  # the card names the averaged files
    mug, _ = _weights(tmp_path / "mug.pt", 2, object_name="mug")
    assert main(["average-weights", str(a), str(mug), "--out", str(out)]) == 1
    assert "not one network" in capsys.readouterr().err

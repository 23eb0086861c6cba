"""Average several weights files of one network into one ("model soup", SWA of finished runs).

The weights of runs that share their start (a continuation and the run it went on from, or
runs from one checkpoint on other renders) usually lie in one basin of the loss; their mean
often generalises better than either, as a stochastic weight average does within one run
(Izmailov et al., 2018; Wortsman et al., 2022). For two CPU continuations of the mustard
bottle's network the mean of the two final weights had a lower median rotation error on
held-out renders than both (its model card,
``models/weights/006_mustard_bottle_dope_lite_small.md``, "How it was made").

Floating-point tensors (weights and the batch-norm running statistics) are averaged in float64
and cast back; integer tensors (``num_batches_tracked``) take their largest value. Averaging
the running statistics is an approximation that holds for weights close to each other; for
distant ones recompute them on training images (``torch.optim.swa_utils.update_bn``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch

from evtrack.errors import ConfigError
from evtrack.models.weights import WeightsError, WeightsRecord, load_weights_file, save_weights

__all__ = ["average_weights"]

# the record fields that must agree for the state dicts to mean the same network and inputs
_SAME = ("arch", "arch_kwargs", "object_name", "cuboid", "input_size", "mean", "std",
         "output_stride")


def average_weights(paths: Sequence[str | Path], out: str | Path,
                    factors: Sequence[float] | None = None) -> Path:
    """Write the (weighted) mean of the weights in ``paths`` to ``out``.

    Args:
        paths: two or more weights files or ``evtrack train`` checkpoints of one architecture,
            object and input normalisation.
        out: the weights file to write (atomically: a temporary file, then a rename).
        factors: one non-negative weight per file (normalised to sum 1); default: equal.

    Returns:
        ``out``. Its record is the first file's, with ``origin`` naming the averaged files,
        ``training["averaged"]`` listing each file with its factor and training facts, and no
        ``metrics`` (measured on none of the averaged networks, they do not hold for the mean).

    Raises:
        WeightsError: fewer than two files, a file that cannot be read, records that differ in
            architecture, object, cuboid, input size or normalisation, or state dicts whose
            keys or shapes differ (the message names the file and what differs).
        ConfigError: ``factors`` of the wrong length, negative or not finite, or summing to
            zero; ``out`` one of the inputs.
    """
    from evtrack.models.factory import create

    paths = [Path(p) for p in paths]
    if any(p.exists() and Path(out).exists() and p.resolve() == Path(out).resolve()
           for p in paths):
        raise ConfigError(f"{out}: the output is one of the inputs; write the mean elsewhere")
    if len(paths) < 2:
        raise WeightsError(", ".join(map(str, paths)) or "(none)",
                           "averaging needs at least two weights files")
    factors = [1.0] * len(paths) if factors is None else [float(f) for f in factors]
    if len(factors) != len(paths):
        raise ConfigError(f"{len(factors)} factors for {len(paths)} weights files")
    if not all(math.isfinite(f) for f in factors) or min(factors) < 0 or sum(factors) <= 0:
        raise ConfigError(f"factors must be finite and >= 0 with a positive sum, got {factors}")
    total = sum(factors)
    loaded = [load_weights_file(p) for p in paths]
    first_record, first_state = loaded[0]
    first = first_record.to_dict()
    for path, (record, state) in zip(paths[1:], loaded[1:], strict=True):
        other = record.to_dict()
        for name in _SAME:
            if other[name] != first[name]:
                raise WeightsError(path, f"record field {name!r} is {other[name]!r}, "
                                         f"{paths[0]} has {first[name]!r}: not one network")
        if set(state) != set(first_state):
            diff = sorted(set(state) ^ set(first_state))[:5]
            raise WeightsError(path, f"state dict keys differ from {paths[0]}'s: {diff}")
        for key, value in state.items():
            if value.shape != first_state[key].shape:
                raise WeightsError(path, f"{key} has shape {tuple(value.shape)}, "
                                         f"{paths[0]}'s {tuple(first_state[key].shape)}")
    mean: dict[str, torch.Tensor] = {}
    for key, value in first_state.items():
        tensors = [state[key] for _, state in loaded]
        if value.is_floating_point():
            acc = sum(f / total * t.double() for f, t in zip(factors, tensors, strict=True))
            mean[key] = acc.to(value.dtype)
        else:
            mean[key] = torch.stack(tensors).amax(0)
    net = create(first_record.arch, **first_record.arch_kwargs)
    net.load_state_dict(mean)
    averaged = [{"file": str(p), "factor": round(f / total, 6), "origin": r.origin,
                 **{k: r.training[k] for k in ("steps", "wall_time_s") if k in r.training}}
                for p, f, (r, _) in zip(paths, factors, loaded, strict=True)]
    descriptions = list(dict.fromkeys(r.training_data for r, _ in loaded if r.training_data))
    record = WeightsRecord.from_dict({
        **first, "created": "",
        "origin": "evtrack average-weights of " + ", ".join(str(p) for p in paths),
        "metrics": {},
        "training": {"averaged": averaged},
        "training_data": " | ".join(descriptions),
    })
    return save_weights(out, net, record)

"""The Triton registration kernel (CUDA) against the tensor registration.

On a GPU (``pytest --device cuda``) the kernel runs compiled; elsewhere, where Triton is
installed, it runs under Triton's interpreter (``TRITON_INTERPRET=1``, in a child process:
the interpreter is chosen when the kernel is defined). Without Triton the tests skip (CPU
installs need not carry it; PyTorch's CUDA builds bring it)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("triton", reason="triton is not installed (it comes with PyTorch's CUDA "
                                     "builds): the Triton registration is not tested here")

HERE = Path(__file__).resolve().parent

# compares register_groups(backend=TritonRegistration()) with the tensor path on the random
# inputs of test_flow_backends (ties, repeats, caps, single edges, cost ties) and on
# collinear events whose tied costs must go to the smaller rank
CHECK = r"""
import sys
import numpy as np
import torch
sys.path.insert(0, {here!r})
from test_flow_backends import _random_registration_input
from evtrack.flow.registration import register_groups
from evtrack.flow.registration_triton import TritonRegistration

dev = torch.device({device!r})


def compare(args, kw):
    a = register_groups(*args, **kw)
    b = register_groups(*(v.to(dev) if torch.is_tensor(v) else v for v in args),
                        backend=TritonRegistration(), **kw)
    b = {{k: getattr(b, k).cpu() for k in a.__dataclass_fields__}}
    for name in ("full_flow", "cost", "used_events", "inliers", "lines"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(b[name].float(), 1e30)), name
    torch.testing.assert_close(a.ratio, b["ratio"], rtol=1e-5, atol=1e-6)
    clear = (a.ratio - 0.05).abs() > 1e-4
    assert torch.equal(a.normal[clear], b["normal"][clear])
    torch.testing.assert_close(a.flow[clear], b["flow"][clear], rtol=1e-4, atol=1e-3,
                               equal_nan=True)
    torch.testing.assert_close(a.normal_dir[clear], b["normal_dir"][clear], rtol=1e-5,
                               atol=1e-5, equal_nan=True)
    return a


for seed in {seeds}:
    group, seq, ordinal, flow, n_groups = _random_registration_input(seed)
    a = compare((group, seq, ordinal, flow, n_groups + 3, 12, 9, 0.05, 10_000),
                dict(refine=True, line_gate=0.35, refine_iters=5, n_ordinals=1024))
    assert int((a.used_events == 12).sum()) >= 1  # the event cap is at work
    assert int(a.normal.sum()) >= 1 and int((~a.normal & (a.lines >= 2)).sum()) >= 1
    assert bool(torch.isnan(a.full_flow[-3:]).all())  # groups without candidates
winners = set()
for trial in range(12):
    rng = np.random.default_rng(trial)
    xs = [0.0, 1.0, 10.0, 13.0, 29.0, 30.0]
    seqs = np.cumsum(rng.integers(1, 1000, len(xs)))
    rows = [(int(seqs[k]), o, c) for k, x in enumerate(xs)
            for o, c in enumerate([(x, 0.0)] + ([(12.9, 1000.0)] if k == 0 else []))]
    args = (torch.zeros(len(rows), dtype=torch.int64),
            torch.tensor([r[0] for r in rows]), torch.tensor([r[1] for r in rows]),
            torch.tensor([r[2] for r in rows], dtype=torch.float32), 1, 64, 48, 0.05, 10_000)
    winners.add(float(compare(args, dict(n_ordinals=8)).full_flow[0, 0]))
assert winners == {{10.0, 13.0}}, winners
print("TRITON-REGISTRATION-OK")
"""


def test_triton_registration_equals_the_tensor_registration(device):
    seeds = [0, 1, 2, 3, 4, 5] if device.type == "cuda" else [0, 3]
    env = dict(os.environ)
    if device.type != "cuda":
        env["TRITON_INTERPRET"] = "1"  # Triton's interpreter runs the kernel on CPU
    code = CHECK.format(here=str(HERE), device=str(device), seeds=seeds)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=900)
    assert out.returncode == 0 and "TRITON-REGISTRATION-OK" in out.stdout, \
        out.stdout[-3000:] + out.stderr[-3000:]


def test_flow_with_the_triton_registration_equals_the_tensor_flow(device):
    """The whole flow on CUDA with ``backend="auto"`` (Triton registration) against
    ``backend="torch"``: the same RoIs, Eq. 3 solutions and costs."""
    if device.type != "cuda":
        pytest.skip("the whole flow through Triton runs on CUDA (--device cuda)")
    from evtrack.flow import FlowConfig, TripletFlow
    from evtrack.flow.backends import resolve
    from evtrack.flow.scenes import translating_texture

    ev, _ = translating_texture((64, 48), velocity=(700.0, 300.0), duration_us=30_000, seed=5)
    out = {}
    for backend in ("torch", "compiled"):
        cfg = FlowConfig(sensor_size=(64, 48), roi_size=16, window_us=2_000, backend=backend,
                         device=str(device))
        assert (resolve(cfg, device).name == "triton") == (backend == "compiled")
        out[backend] = TripletFlow(cfg)(ev.to(device))
    a, b = out["torch"], out["compiled"]
    assert len(a) > 20
    for name in ("full_flow", "cost", "support", "roi", "window", "n_events"):
        assert torch.equal(torch.nan_to_num(getattr(a, name).float(), 1e30),
                           torch.nan_to_num(getattr(b, name).float(), 1e30)), name
    torch.testing.assert_close(a.flow, b.flow, rtol=1e-4, atol=1e-3)
